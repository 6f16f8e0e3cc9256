"""One cell of the ablation (Table II): a variant of the method trained, meshed and scored
on one scene, from files to files. The variant's settings are partial sections merged over
the main params (``pipeline.config.ablation.VariantConfig``); its init cloud is the init stage's
dense cloud (``mvs``), or the baseline stage's sparse SIFT cloud (``sfm``) or random
points in the bounding sphere (``random``)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.ablation import AblationConfig, VariantConfig
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.loss import LossConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import merged_section, section
from pipeline.errors import ConfigError
from pipeline.evaluation.record import SceneMetrics
from pipeline.measure import measure
from pipeline.rasterizer import resolve_backend
from pipeline.runs.mesh import mesh_surfels_dir
from pipeline.runs.optimize import run_optimize, timing_report
from pipeline.runs.score import scene_metrics


def variant_configs(params: dict, variant: str) -> tuple[VariantConfig, OptimizeConfig, LossConfig, MeshConfig]:
    """The variant's own settings and the optimize, loss and mesh sections it runs with."""
    ablation = section(AblationConfig, "ablation", params)
    if variant not in ablation.variants:
        raise ConfigError(f"ablation variant {variant!r} is not defined (defined: {sorted(ablation.variants)})")
    v = ablation.variants[variant]
    return (v, merged_section(OptimizeConfig, "optimize", params, v.optimize),
            merged_section(LossConfig, "loss", params, v.loss), merged_section(MeshConfig, "mesh", params, v.mesh))


def run_variant(name: str, variant: str, params: dict, scene_dir: str | Path, src_dir: str | Path,
                gt_dir: str | Path | None, init_dirs: dict[str, str | Path], priors_dir: str | Path,
                out_dir: str | Path, report: str | Path, input_views: list[int]) -> SceneMetrics:
    """Train, mesh and score ``variant`` on scene ``name``: writes ``out_dir/surfels`` and
    ``out_dir/mesh`` (same bytes for the same inputs), the metrics to ``report`` and the
    training time to ``report`` with suffix ``.train.json``. ``init_dirs`` maps each init
    source (mvs, sfm, random) to the folder holding its ``points.ply``. Returns the metrics."""
    v, opt, loss, mesh_cfg = variant_configs(params, variant)
    out_dir, report = Path(out_dir), Path(report)
    surfels_dir, mesh_dir = out_dir / "surfels", out_dir / "mesh"
    timing_path = report.with_suffix(".train.json")
    with measure(reset_peak=False) as usage:
        result = run_optimize(scene_dir, init_dirs[v.init], priors_dir, surfels_dir, opt, loss,
                              checkpoint=out_dir.parent / f".{out_dir.name}.ckpt.pt", live_dir=None, progress=False)
    atomic.write_text(timing_path, json.dumps(timing_report(result, usage.as_dict(), opt.preset), indent=2) + "\n")

    backend = resolve_backend(opt.backend)
    mesh_surfels_dir(scene_dir, surfels_dir, mesh_dir, mesh_cfg, backend, init_dirs[v.init])

    metrics = scene_metrics(name, scene_dir, src_dir, gt_dir, surfels_dir, mesh_dir, timing_path,
                            section(EvaluateConfig, "evaluate", params), opt, mesh_cfg, input_views, backend)
    metrics = dataclasses.replace(metrics, variant={"name": variant, "init": v.init, "optimize": v.optimize,
                                                    "loss": v.loss, "mesh": v.mesh})
    metrics.write(report)
    return metrics
