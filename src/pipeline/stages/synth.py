"""``gcgs synth NAME --out DIR``: render a synthetic scene with exact ground truth."""
from __future__ import annotations

import argparse


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", nargs="?", help="scene name (see --list)")
    p.add_argument("--out", help="output folder (DTU layout, ground truth in OUT/gt)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=800)
    p.add_argument("--height", type=int, default=600)
    p.add_argument("--cameras", default="data/raw/dtu/scan24", help="scan whose 49 cameras are used")
    p.add_argument("--list", action="store_true", help="print the scene names and exit")


def run(args: argparse.Namespace) -> int:
    from pipeline.synth import SCENES, write_synth_scene

    if args.list:
        for name, (scan_id, _, stresses) in SCENES.items():
            print(f"{name}\t(scan id {scan_id}) {stresses}")
        return 0
    if not args.name or not args.out:
        raise ValueError("give a scene NAME and --out DIR (or --list)")
    write_synth_scene(args.name, args.out, seed=args.seed, width=args.width, height=args.height,
                      cameras_dir=args.cameras)
    return 0
