"""``gcgs score``: the per-scene metrics of the method (the ``evaluate`` stage): DTU Chamfer
where the scene has ground truth, else held-out-view IoU / PSNR, plus training time, time
per iteration, surfel count and peak memory -> ``reports/metrics/NAME.json``."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.data import DataConfig
from pipeline.data import dtu
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.config.scenes import scene_entry
from pipeline.rasterizer import resolve_backend
from pipeline.runs.score import scene_metrics


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="scene name (a key of params `scenes`: its src and gt)")
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--surfels-dir", required=True, help="optimize stage output")
    p.add_argument("--mesh-dir", required=True, help="mesh stage output")
    p.add_argument("--train-timing", required=True, help="the optimize stage's timing JSON")
    p.add_argument("--out", required=True, help="metrics JSON to write")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    atomic.check_output_file(args.out, inputs=(args.train_timing, args.scene, args.surfels_dir, args.mesh_dir))
    params = load_params(args.params)
    entry = scene_entry(params, args.name)
    opt = section(OptimizeConfig, "optimize", params)
    metrics = scene_metrics(args.name, args.scene, entry.src, entry.gt, args.surfels_dir, args.mesh_dir,
                            args.train_timing, section(EvaluateConfig, "evaluate", params), opt,
                            section(MeshConfig, "mesh", params), dtu.prepared_views(args.scene) or section(DataConfig, "data", params).views,
                            resolve_backend(opt.backend))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    metrics.write(args.out)
    m = metrics.to_json()
    summary = {k: v for k, v in (m.get("chamfer") or m["heldout"]).items() if k not in ("per_view", "counts")}
    print(f"score {args.name}: {json.dumps(summary)} -> {args.out}")
    return 0
