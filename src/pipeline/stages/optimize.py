"""``gcgs optimize``: train 2D Gaussian surfels on a prepared scene (docs/optimize.md).

Writes ``OUT/surfels.ply`` (2DGS attribute layout, world frame, mm) and ``OUT/train.json``.
Timings, peak memory and the time split go to ``--metrics`` (JSON), the training curves to
``--live-dir`` (DVCLive's layout). A checkpoint in ``--checkpoint`` (outside the DVC output, which
DVC deletes before a run) lets an interrupted run resume.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.measure import measure
from pipeline.runs.optimize import check_side_paths, default_side_paths, run_optimize, timing_report


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--init-dir", required=True, help="init stage output (points.ply)")
    p.add_argument("--priors-dir", required=True, help="priors stage output (normals/, features/)")
    p.add_argument("--out-dir", required=True, help="writes surfels.ply and train.json")
    p.add_argument("--checkpoint", default=None, help="checkpoint file (default: .OUT.ckpt.pt beside OUT)")
    p.add_argument("--metrics", default=None, help="timings JSON (default: OUT.timing.json beside OUT)")
    p.add_argument("--live-dir", default=None, help="training curves folder (default: OUT.curves beside OUT)")
    p.add_argument("--iterations", type=int, default=None, help="default: optimize.iterations")
    p.add_argument("--backend", choices=OptimizeConfig.BACKENDS, default=None, help="default: optimize.backend")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    cfg = section(OptimizeConfig, "optimize", params, {"iterations": args.iterations, "backend": args.backend})
    loss = section(LossConfig, "loss", params)
    name = Path(args.out_dir).name
    side = default_side_paths(args.out_dir)
    metrics, checkpoint = args.metrics or side["metrics"], args.checkpoint or side["checkpoint"]
    live_dir = args.live_dir or side["live_dir"]
    # before hours of training, not after
    check_side_paths(args.out_dir, (args.scene, args.init_dir, args.priors_dir), checkpoint, live_dir, metrics)
    with measure(reset_peak=False) as usage:
        result = run_optimize(args.scene, args.init_dir, args.priors_dir, args.out_dir, cfg, loss,
                              checkpoint=checkpoint, live_dir=live_dir, progress=not args.no_progress)
    atomic.write_text(metrics, json.dumps(timing_report(result, usage.as_dict(), cfg.preset), indent=2) + "\n")
    print(f"optimize {name}: {result.iterations} iterations ({cfg.preset}, {result.backend}) in {usage.wall_s:.0f} s, "
          f"{result.num_init} -> {result.params.num} surfels -> {args.out_dir}")
    return 0
