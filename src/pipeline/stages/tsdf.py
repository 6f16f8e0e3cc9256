"""``gcgs tsdf``: TSDF-fuse an init folder's depth maps (``depth/*.npz``) into a cleaned
mesh (world mm). The classical baseline mesh: mvs depth maps -> TSDF -> largest
component(s).

Sizes are in unit-sphere radii, times the scene's scale_mat radius in mm (2DGS on DTU:
voxel 0.004, truncation 0.016, keep 1 cluster).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from pipeline import geometry
from pipeline.data.dtu import load_scene
from pipeline.data.scene import SceneError
from pipeline.init.io import read_depth
from pipeline.meshing import tsdf
from pipeline.measure import peak_rss_mb


def mesh_from_init(init_dir: str | Path, scene_dir: str | Path, voxel_norm: float = 0.004, trunc_norm: float = 0.016,
                   num_clusters: int = 1, min_fraction: float = 0.0) -> tuple[tsdf.Mesh, dict]:
    """Fuse the depth maps of ``init_dir`` (cameras from the files, colours from the scene)."""
    init_dir, scene_dir = Path(init_dir), Path(scene_dir)
    files = sorted((init_dir / "depth").glob("*.npz"))
    if not files:
        raise SceneError(f"{init_dir / 'depth'}: no depth maps (is this the output of a depth backend?)")
    scene = load_scene(scene_dir, view_ids=None)
    maps = [read_depth(f) for f in files]
    by_id = dict(zip(scene.view_ids, range(scene.num_views)))
    for f, m in zip(files, maps):
        if m.view_id not in by_id:
            raise SceneError(f"{f}: view {m.view_id} is not an image of {scene_dir}")
        if m.depth_mm.shape != (scene.height, scene.width):
            raise SceneError(f"{f}: depth size {m.depth_mm.shape[::-1]} differs from the scene's "
                             f"{scene.width}x{scene.height}")
    voxel, trunc = tsdf.default_sizes_mm(scene.norm_scale_mm, voxel_norm, trunc_norm)
    # Farthest depth worth integrating: the far side of the scene sphere from any camera.
    centre = scene.norm_to_world[:3, 3]
    depth_max = max(np.linalg.norm(geometry.camera_center(m.world_to_cam) - centre) for m in maps) + scene.norm_scale_mm
    mesh = tsdf.fuse_depth_maps(
        np.stack([np.where(m.valid, m.depth_mm, 0.0) for m in maps]), np.stack([m.K for m in maps]),
        np.stack([m.world_to_cam for m in maps]), np.stack([scene.images[by_id[m.view_id]] for m in maps]),
        voxel, trunc, depth_max)
    raw = len(mesh.triangles)
    mesh = tsdf.keep_largest_components(mesh, num_clusters, min_fraction)
    info = {"voxel_mm": voxel, "trunc_mm": trunc, "depth_max_mm": float(depth_max), "views": [m.view_id for m in maps],
            "triangles_fused": raw, "triangles_kept": len(mesh.triangles), "vertices": len(mesh.vertices_mm),
            "num_clusters": num_clusters, "min_fraction": min_fraction}
    return mesh, info


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--init-dir", required=True, help="output folder of `gcgs init` (with depth/)")
    p.add_argument("--scene", required=True, help="the scene folder (colours, scale)")
    p.add_argument("--out", required=True, help="mesh PLY to write (world mm)")
    p.add_argument("--voxel-norm", type=float, default=0.004, help="voxel, unit-sphere radii")
    p.add_argument("--trunc-norm", type=float, default=0.016, help="SDF truncation, unit-sphere radii")
    p.add_argument("--num-clusters", type=int, default=1, help="keep this many largest components")
    p.add_argument("--min-fraction", type=float, default=0.0,
                   help="... each with at least this fraction of the largest one's triangles")


def run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    mesh, info = mesh_from_init(args.init_dir, args.scene, args.voxel_norm, args.trunc_norm, args.num_clusters,
                                args.min_fraction)
    tsdf.write_mesh(args.out, mesh)
    info.update(time_s=round(time.perf_counter() - t0, 2),
                peak_rss_mb=peak_rss_mb())
    print(json.dumps(info))
    return 0
