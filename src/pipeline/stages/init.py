"""``gcgs init``: the initial point cloud of a prepared scene (docs/init.md).

Writes ``OUT/points.ply``, ``OUT/depth/{view:03d}.npz`` (depth backends) and
``OUT/init.json``, all into a temporary sibling folder renamed into place at the end.
"""
from __future__ import annotations

import argparse
import json

from pipeline import atomic
from pipeline.config.init import InitConfig
from pipeline.config.params import load_params, section
from pipeline.errors import print_warning
from pipeline.init.backends import match_summary
from pipeline.measure import measure
from pipeline.runs.init import run_init


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder (DTU layout)")
    p.add_argument("--backend", choices=InitConfig.BACKENDS, default=None, help="default: init.backend")
    p.add_argument("--model", default=None, help="ONNX model file (mast3r backend); default: init.mast3r.model")
    p.add_argument("--out-dir", required=True, help="output folder (points.ply, depth/, init.json)")
    p.add_argument("--metrics", default=None, help="also write the run's time and peak memory to this JSON")
    p.add_argument("--params", default=None, help="params.yaml to read `init` from (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    cfg = section(InitConfig, "init", load_params(args.params), {"backend": args.backend, "mast3r.model": args.model})
    if args.metrics:
        atomic.check_output_file(args.metrics, inputs=(args.scene, args.model))
    with measure(reset_peak=False) as usage:
        _, info = run_init(args.scene, args.out_dir, cfg)
    print(f"init {cfg.backend}: {info['num_points']} points in {usage.wall_s:.2f} s "
          f"(peak RSS {usage.peak_rss_mb} MB) -> {args.out_dir}", *match_summary(info), sep="\n")
    for warning in info.get("warnings", []):
        print_warning(f"{args.scene}: {warning}")
    if args.metrics:  # timings live here, not in the output (same inputs, same bytes)
        atomic.write_text(args.metrics, json.dumps({"backend": cfg.backend, **usage.as_dict()}, indent=2) + "\n")
    return 0
