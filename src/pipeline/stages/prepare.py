"""``gcgs prepare``: load a DTU-layout scan, check it, and write the training views at the
training resolution (intrinsics scaled consistently) as a new DTU-layout scene.

Only the selected views' images are written; every camera and mask of the source is kept
(so held-out views stay usable for mask culling and checks), scaled to the new size.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline import geometry
from pipeline.config import DataConfig, load_params, section
from pipeline.data import dtu
from pipeline.data.scene import Scene


def prepare_scene(
    src: str | Path, out: str | Path, cfg: DataConfig, name: str | None = None, extra_meta: dict | None = None
) -> Scene:
    """Load ``src`` at ``cfg.views`` / ``cfg.width x cfg.height`` and write it to ``out``."""
    src = Path(src)
    scene = dtu.load_scene(src, view_ids=cfg.views, resolution=(cfg.width, cfg.height), name=name)
    cams = dtu.load_cameras(src)
    # All cameras share the stored image size of the source; scale every one like the views.
    stored_w, stored_h = dtu.stored_image_size(src)
    sx, sy = cfg.width / stored_w, cfg.height / stored_h
    K = {v: geometry.scale_intrinsics(cams.K[v], sx, sy) for v in cams.ids}
    masks = None
    if scene.masks is not None:
        masks = {v: dtu.resize_mask(m, cfg.width, cfg.height) for v, m in dtu.load_masks(src).items()}
    meta = dict(scene.meta)
    meta.update(
        name=scene.name,
        scan_id=scene.scan_id,
        prepared_from=str(src),
        views=scene.view_ids,
        width=cfg.width,
        height=cfg.height,
        **(extra_meta or {}),
    )
    dtu.write_scene(
        out,
        images=dict(zip(scene.view_ids, scene.images)),
        K=K,
        world_to_cam=cams.world_to_cam,
        norm_to_world=cams.norm_to_world,
        masks=masks,
        meta=meta,
    )
    return scene


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--src", required=True, help="DTU-layout scan folder")
    p.add_argument("--out", required=True, help="output scene folder")
    p.add_argument("--name", default=None, help="scene name (default: from scene.json or the folder)")
    p.add_argument("--params", default=None, help="params.yaml to read `data` from (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    cfg = section(DataConfig, "data", params)
    scene = prepare_scene(args.src, args.out, cfg, name=args.name)
    n_fg = "no masks" if scene.masks is None else f"mask coverage {np.mean(scene.masks):.1%}"
    print(f"prepared {scene.name}: views {scene.view_ids} at {cfg.width}x{cfg.height}, {n_fg} -> {args.out}")
    return 0
