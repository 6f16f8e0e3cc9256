"""A rendered textured relief plate in the DTU layout with its exact depth written as an
init stage output (a tiny input for the priors stage and its benchmark)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.data import dtu
from pipeline.init.io import DepthMap, depth_path, write_depth


def write_relief_scene(root: Path, camera_source: Path, views: tuple[int, ...], width: int, height: int):
    """Write ``root/scene`` (DTU layout) and ``root/init`` (depth/*.npz); returns
    ``(scene_dir, init_dir, relief)`` where ``relief`` holds the ground truth."""
    from pipeline.benchmarks.relief_scene import textured_relief_scene

    scan = dtu.load_scene(camera_source, view_ids=list(views), resolution=(width, height), with_masks=False)
    sc = textured_relief_scene(scan.K, scan.world_to_cam, width, height, scan.norm_to_world[:3, 3])
    scene_dir = dtu.write_scene(root / "scene", images=dict(zip(views, sc.images)), K=dict(zip(views, sc.K)),
                                world_to_cam=dict(zip(views, sc.world_to_cam)), norm_to_world=scan.norm_to_world,
                                meta={"name": "relief"})
    init_dir = root / "init"
    for v, K, T, d in zip(views, sc.K, sc.world_to_cam, sc.depth_mm):
        ok = d > 0
        write_depth(depth_path(init_dir, v),
                    DepthMap(v, np.where(ok, d, 0).astype(np.float32), ok.astype(np.float32), ok, K, T))
    return scene_dir, init_dir, sc
