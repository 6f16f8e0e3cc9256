"""``gcgs prepare``: load a capture (DTU scan, COLMAP or nerfstudio folder; docs/inputs.md), check it, and write the training views at the
training resolution (intrinsics scaled consistently) as a new DTU-layout scene
(:mod:`pipeline.data.prepare`). Views default to params ``data.views`` for a DTU scan and
to every image for a COLMAP or nerfstudio capture; size defaults to params ``data``; ``--width``
alone derives the height from the source's aspect ratio, and a size in another aspect
ratio is refused. A capture without masks gets masks derived from its MVS depth
(``--masks``, :mod:`pipeline.runs.prepare`; docs/inputs.md, "Without masks").
"""
from __future__ import annotations

import argparse
from dataclasses import replace

import numpy as np

from pipeline.config.data import DataConfig
from pipeline.config.init import InitConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.params import load_params, section
from pipeline.data.dtu import load_scene
from pipeline.data.prepare import height_for_width, input_views
from pipeline.runs.prepare import MASKS, prepare_with_masks


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--src", required=True, help="capture folder: DTU scan, COLMAP (images/, sparse/0/) or nerfstudio (transforms.json)")
    p.add_argument("--out", required=True, help="output scene folder")
    p.add_argument("--name", default=None, help="scene name (default: from scene.json or the folder)")
    p.add_argument("--views", type=int, nargs="+", default=None, help="view ids to train on (default: data.views for a DTU scan, every image of any other capture)")
    p.add_argument("--width", type=int, default=None,
                   help="training width (default: data.width); alone, the height keeps the source's aspect")
    p.add_argument("--height", type=int, default=None, help="training height (default: data.height)")
    p.add_argument("--masks", choices=MASKS, default="auto",
                   help="auto (default): the capture's masks, derived from its MVS depth where it has none; capture; "
                        "derive; none (docs/inputs.md)")
    p.add_argument("--no-masks", action="store_true",
                   help="leave the source's masks out, as for a capture without masks: with --masks auto they are "
                        "derived (docs/inputs.md)")
    p.add_argument("--sphere", type=float, nargs=4, default=None, metavar=("CX", "CY", "CZ", "RADIUS"),
                   help="the object's unit sphere (scale_mat) in the input's world frame and units, in place of "
                        "the one the layout gives or derives (docs/inputs.md)")
    p.add_argument("--params", default=None,
                   help="params.yaml to read `data` (and `init`, `mesh` for derived masks) from (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    height = args.height
    if args.width is not None and height is None:
        height = height_for_width(args.src, args.width)
    params = load_params(args.params)
    cfg = section(DataConfig, "data", params, {"width": args.width, "height": height})
    cfg = replace(cfg, views=input_views(args.src, args.views, cfg.views))
    masks = "derive" if args.no_masks and args.masks in ("auto", "capture") else args.masks
    scene, derived = prepare_with_masks(args.src, args.out, cfg, masks, section(InitConfig, "init", params),
                                        section(MeshConfig, "mesh", params), name=args.name, sphere=args.sphere)
    scene = scene if scene is not None else load_scene(args.out, view_ids=None)
    n_fg = "no masks" if scene.masks is None else f"mask coverage {np.mean(scene.masks):.1%}"
    if derived is not None:
        fallbacks = sum(v["method"] == "fallback_region" for v in derived["views"].values())
        n_fg = f"derived masks, coverage {np.mean(scene.masks):.1%} ({fallbacks} fell back to the region's silhouette)"
    print(f"prepared {scene.name}: views {scene.view_ids} at {cfg.width}x{cfg.height}, {n_fg} -> {args.out}")
    return 0
