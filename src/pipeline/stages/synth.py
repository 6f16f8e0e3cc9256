"""``gcgs synth NAME --out DIR``: render a synthetic scene with exact ground truth
(:func:`pipeline.synth.write_synth_scene`); seed, size and cameras default to params ``synth``."""
from __future__ import annotations

import argparse

from pipeline.config.params import load_params, section
from pipeline.config.synth import SynthConfig
from pipeline.errors import InputError


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", nargs="?", help="scene name (see --list)")
    p.add_argument("--out", help="output folder (DTU layout, ground truth in OUT/gt)")
    p.add_argument("--seed", type=int, default=None, help="default: synth.seed")
    p.add_argument("--width", type=int, default=None, help="default: synth.width")
    p.add_argument("--height", type=int, default=None, help="default: synth.height")
    p.add_argument("--cameras", default=None, help="scan whose 49 cameras are used (default: synth.camera_source)")
    p.add_argument("--params", default=None, help="params.yaml to read `synth` from (default: ./params.yaml)")
    p.add_argument("--list", action="store_true", help="print the scene names and exit")


def run(args: argparse.Namespace) -> int:
    from pipeline.synth import SCENES, write_synth_scene

    if args.list:
        for name, (scan_id, _, stresses) in SCENES.items():
            print(f"{name}\t(scan id {scan_id}) {stresses}")
        return 0
    if not args.name or not args.out:
        raise InputError("give a scene NAME and --out DIR (or --list)")
    if args.name not in SCENES:
        raise InputError(f"unknown synthetic scene {args.name!r}; choose from {', '.join(SCENES)}")
    cfg = section(SynthConfig, "synth", load_params(args.params),
                  {"seed": args.seed, "width": args.width, "height": args.height, "camera_source": args.cameras})
    write_synth_scene(args.name, args.out, seed=cfg.seed, width=cfg.width, height=cfg.height,
                      cameras_dir=cfg.camera_source)
    return 0
