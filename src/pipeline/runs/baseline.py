"""The classical baseline of one scene (docs/init.md); the table of several scenes is in
:mod:`pipeline.reports.baseline_table`.

The init stage has already run the default backend (``init.backend``): its cloud and depth
maps are read from its folder, its time and peak memory from its ``init.json``. What no
stage computes runs here, each step in its own fresh process
(:func:`pipeline.measure.run_in_child`) so that its time and peak memory are its own,
imports included: the other backends' clouds, the TSDF mesh of the default backend's
depth maps (the role COLMAP plays in the GCGS paper's Table I), and that mesh's DTU
Chamfer distance. Every cloud is scored against the ground truth
(:mod:`pipeline.evaluation.clouds`) when the scene has one.
"""
from __future__ import annotations

import dataclasses
import json
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline import atomic
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.init import InitConfig
from pipeline.config.mesh import MeshConfig
from pipeline.data import dtu
from pipeline.evaluation import gt
from pipeline.evaluation.clouds import cloud_metrics
from pipeline.evaluation.record import Chamfer
from pipeline.init.backends import BACKEND_MODULES
from pipeline.init.io import read_ply
from pipeline.measure import Usage, run_in_child
from pipeline.runs.baseline_steps import backend_cloud, mesh_chamfer, tsdf_mesh

NO_MAST3R_MODEL = ("not run: no MASt3R ONNX model file (weights cannot be downloaded here; see docs/init.md "
                   "for the export script)")
MESH, MESH_METRICS = "mvs_tsdf.ply", "mvs_tsdf_metrics.json"


def _figures(usage: Usage) -> dict:
    d = usage.as_dict()
    return {k: d[k] for k in ("wall_s", "cpu_s", "peak_rss_mb")}


def _step(fn: Callable, *args) -> tuple[dict, Any]:
    """Run one step in a child: ({"status", "run"}, its result); a failure is reported and
    the other steps still run (its traceback goes to stderr)."""
    try:
        result, usage = run_in_child(fn, *args)
    except Exception as exc:  # noqa: BLE001 -- reported as the step's status; the stage then exits 1
        traceback.print_exception(exc, file=sys.stderr)
        return {"status": f"failed: {type(exc).__name__}: {exc}"}, None
    return {"status": "ok", "run": _figures(usage)}, result


def baseline_scene(scene_dir: str | Path, init_dir: str | Path, out_dir: str | Path, gt_dir: str | Path | None,
                   init_cfg: InitConfig, eval_cfg: EvaluateConfig, mesh_cfg: MeshConfig,
                   init_usage: dict | None = None, log: Callable[[str], None] = print) -> dict:
    """The baseline of one scene (module docstring); clouds, mesh and metrics go to
    ``out_dir`` (written whole at the end). Returns the report (JSON-ready)."""
    scene_dir, init_dir, out_dir = Path(scene_dir), Path(init_dir), Path(out_dir)
    info_path = init_dir / "init.json"
    if not info_path.is_file():
        raise FileNotFoundError(f"{info_path}: the init stage's output not found (run `gcgs init` / `dvc repro init`)")
    init_info = json.loads(info_path.read_text())
    default = init_info.get("backend")
    if default != init_cfg.backend:
        raise ValueError(f"{info_path}: written by backend {default!r} but params init.backend is "
                         f"{init_cfg.backend!r} (rerun the init stage)")
    if not (scene_dir / "cameras_sphere.npz").is_file():
        raise FileNotFoundError(f"{scene_dir}: prepared scene not found (run `gcgs prepare` / `dvc repro prepare`)")
    ground = gt.read_ground_truth(gt_dir, dtu.read_meta(scene_dir).get("scan_id")) if gt_dir else None
    report: dict = {"scene_dir": str(scene_dir), "init_dir": str(init_dir), "gt": None if gt_dir is None else str(gt_dir),
                    "init_config": dataclasses.asdict(init_cfg), "evaluate_config": dataclasses.asdict(eval_cfg),
                    "backends": {}}
    with atomic.atomic_dir(out_dir, "baseline", inputs=(scene_dir, init_dir, gt_dir)) as tmp:
        for backend in BACKEND_MODULES:
            if backend == default:
                entry: dict = {"status": "ok", "source": f"init stage ({init_dir})",
                               "init": {k: (init_usage or {}).get(k) for k in ("wall_s", "cpu_s", "peak_rss_mb")},
                               "init_facts": {k: v for k, v in init_info.items() if k not in ("config", "scene")}}
                cloud_path = init_dir / "points.ply"
            elif backend == "mast3r" and not init_cfg.mast3r.model:
                report["backends"][backend] = {"status": NO_MAST3R_MODEL}
                continue
            else:
                cloud_path = tmp / backend / "points.ply"
                step, facts = _step(backend_cloud, scene_dir, backend, init_cfg, cloud_path)
                entry = {"status": step["status"]}
                if facts is not None:
                    entry.update(init=step["run"], init_facts=facts)
            if entry["status"] == "ok" and ground is not None:
                entry["cloud"] = cloud_metrics(read_ply(cloud_path).points_mm, ground, eval_cfg)
            report["backends"][backend] = entry
            log(f"{backend}: {entry['status']}"
                + (f", {entry['init']['wall_s']} s, {entry['init']['peak_rss_mb']} MB" if "init" in entry else "")
                + (f", median {entry['cloud']['median_to_surface_mm']:.3f} mm" if "cloud" in entry else ""))

        if not list((init_dir / "depth").glob("*.npz")):
            report["tsdf"] = {"status": f"not run: the {default} backend writes no depth maps"}
        else:
            step, facts = _step(tsdf_mesh, init_dir, scene_dir, mesh_cfg, tmp / MESH)
            report["tsdf"] = {**step, **({"facts": facts} if facts is not None else {})}
            if facts is not None and ground is not None:
                step, _ = _step(mesh_chamfer, tmp / MESH, scene_dir, Path(gt_dir), eval_cfg, facts["views"],
                                tmp / MESH_METRICS)
                report["evaluate"] = step
                if step["status"] == "ok":
                    m = json.loads((tmp / MESH_METRICS).read_text())
                    step["metrics"] = Chamfer.of(m).to_json()
        log(f"tsdf: {report['tsdf']['status']}"
            + (f", overall {report['evaluate']['metrics']['overall_mm']} mm" if "metrics" in report.get("evaluate", {})
               else ""))
    return report


def failed_steps(report: dict) -> list[str]:
    """The steps of a scene report that failed."""
    steps = {**{f"init {b}": e for b, e in report["backends"].items()},
             "tsdf": report.get("tsdf", {}), "evaluate": report.get("evaluate", {})}
    return [name for name, e in steps.items() if e.get("status", "").startswith("failed")]
