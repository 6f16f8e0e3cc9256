"""The training half of an ablation cell (Table II): the variant's surfels trained on one
scene, from files to files. Its settings are partial sections merged over the main params
(``pipeline.config.variants.variant_training``); its init cloud is the init stage's dense
cloud (``mvs``), or the baseline stage's sparse SIFT cloud (``sfm``) or random points in
the bounding sphere (``random``). Meshing and scoring are :mod:`pipeline.runs.variant_score`,
a stage of their own, so that a change to them does not retrain the cells."""
from __future__ import annotations

import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.variants import training_report, variant_training
from pipeline.measure import measure
from pipeline.runs.optimize import run_optimize, timing_report


def train_variant(variant: str, params: dict, scene_dir: str | Path, init_dirs: dict[str, Path],
                  priors_dir: str | Path, out_dir: str | Path, report: str | Path) -> None:
    """Train ``variant``: writes ``out_dir/surfels`` (same bytes for the same inputs) and the
    training time to :func:`~pipeline.config.variants.training_report` of ``report``."""
    v, opt, loss = variant_training(params, variant)
    out_dir = Path(out_dir)
    atomic.check_output_file(training_report(report), inputs=(scene_dir, init_dirs[v.init], priors_dir))
    with measure(reset_peak=False) as usage:
        result = run_optimize(scene_dir, init_dirs[v.init], priors_dir, out_dir / "surfels", opt, loss,
                              checkpoint=out_dir.parent / f".{out_dir.name}.ckpt.pt", live_dir=None, progress=False)
    atomic.write_text(training_report(report), json.dumps(timing_report(result, usage.as_dict(), opt.preset), indent=2) + "\n")
