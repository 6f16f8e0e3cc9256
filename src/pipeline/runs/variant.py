"""One whole ablation cell, as sweeps run it (``gcgs variant``; scripts/speed_accuracy.py):
the variant trained (:mod:`pipeline.runs.variant_train`), then meshed and scored
(:mod:`pipeline.runs.variant_score`). DVC runs the two halves as stages of their own."""
from __future__ import annotations

from pathlib import Path

from pipeline.errors import MissingInputError
from pipeline.evaluation.record import SceneMetrics
from pipeline.runs.variant_score import score_variant
from pipeline.runs.variant_train import train_variant


def run_variant(name: str, variant: str, params: dict, scene_dir: str | Path, src_dir: str | Path,
                gt_dir: str | Path | None, init_dirs: dict[str, Path], priors_dir: str | Path,
                out_dir: str | Path, report: str | Path, input_views: list[int]) -> SceneMetrics:
    """Train, mesh and score ``variant`` on scene ``name``: writes ``out_dir/surfels`` and
    ``out_dir/mesh`` (same bytes for the same inputs), the metrics to ``report`` and the
    training time beside it (``.train.json``). Returns the metrics. A missing ``gt_dir`` is an
    error before the training, not after it (a sweep cell trains for up to an hour)."""
    if gt_dir is not None and not Path(gt_dir).is_dir():
        raise MissingInputError(f"{gt_dir}: ground-truth folder not found (run from the repository root, "
                                "or `dvc repro synth` first); nothing was trained")
    train_variant(variant, params, scene_dir, init_dirs, priors_dir, out_dir, report)
    return score_variant(name, variant, params, scene_dir, src_dir, gt_dir, init_dirs, out_dir, report, input_views)
