"""The scoring half of an ablation cell (Table II): the variant's trained surfels
(:mod:`pipeline.runs.variant_train`) meshed and scored on one scene, from files to files."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from pipeline import atomic
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.params import section
from pipeline.config.variants import training_report, variant_configs
from pipeline.evaluation.record import SceneMetrics
from pipeline.rasterizer import resolve_backend
from pipeline.runs.mesh import mesh_surfels_dir
from pipeline.runs.score import scene_metrics


def score_variant(name: str, variant: str, params: dict, scene_dir: str | Path, src_dir: str | Path,
                  gt_dir: str | Path | None, init_dirs: dict[str, Path], out_dir: str | Path, report: str | Path,
                  input_views: list[int]) -> SceneMetrics:
    """Mesh ``out_dir/surfels`` of ``variant`` on scene ``name`` into ``out_dir/mesh`` and
    write its metrics to ``report`` (the training time read from beside it, ``.train.json``).
    ``init_dirs`` as :func:`pipeline.config.variants.init_sources`. Returns the metrics."""
    v, opt, _, mesh_cfg = variant_configs(params, variant)
    out_dir, report = Path(out_dir), Path(report)
    surfels_dir, mesh_dir = out_dir / "surfels", out_dir / "mesh"
    backend = resolve_backend(opt.backend)
    atomic.check_output_file(report, inputs=(scene_dir, src_dir, gt_dir, surfels_dir, init_dirs[v.init]))
    mesh_surfels_dir(scene_dir, surfels_dir, mesh_dir, mesh_cfg, backend, init_dirs[v.init])
    metrics = scene_metrics(name, scene_dir, src_dir, gt_dir, surfels_dir, mesh_dir, training_report(report),
                            section(EvaluateConfig, "evaluate", params), opt, mesh_cfg, input_views, backend)
    metrics = dataclasses.replace(metrics, variant={"name": variant, "init": v.init, "optimize": v.optimize,
                                                    "loss": v.loss, "mesh": v.mesh})
    metrics.write(report)
    return metrics
