"""Rendered depth error at the input views, split by how many of the other input views see
the surface there (docs/optimize.md, "The strips are the surface fewer than three views see").

For each input view of a synthetic scene, every pixel inside the mask where both the GT and
the surfels have depth: its GT point is seen by another input view when it projects inside
that view and the view's GT depth there is within ``--tol-mm`` of the point's depth. Prints,
per view and per count of other views, the share of the pixels and the shares rendered more
than ``--off-mm`` in front of / behind the GT.

    python scripts/depth_error_by_views.py synth_thin [--surfels data/surfels/synth_thin/surfels.ply]
"""
from __future__ import annotations

import argparse

import numpy as np

from pipeline import geometry
from pipeline.data.dtu import load_scene
from pipeline.evaluation import gt
from pipeline.evaluation.depth_error import gt_depths_mm
from pipeline.meshing.surfels import render_depths_mm
from pipeline.optimize.surfels import read_surfel_ply


def other_views_seeing(truth_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, i: int, ys: np.ndarray,
                       xs: np.ndarray, tol_mm: float) -> np.ndarray:
    """For view ``i``'s pixels ``(ys, xs)`` with GT depth, how many other views see their GT
    point (inside the image, GT depth there within ``tol_mm`` of the point's)."""
    H, W = truth_mm[i].shape
    P = geometry.backproject_depth(K[i], world_to_cam[i], truth_mm[i])[ys, xs]
    count = np.zeros(len(xs), np.int64)
    for j in range(len(truth_mm)):
        if j == i:
            continue
        uv, z = geometry.project(K[j], world_to_cam[j], P)
        u, v = np.rint(uv[:, 0]).astype(np.int64), np.rint(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        seen_depth = np.zeros(len(xs))
        seen_depth[inside] = truth_mm[j][v[inside], u[inside]]
        count += inside & (np.abs(seen_depth - z) < tol_mm)
    return count


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--surfels", default=None, help="default: data/surfels/SCENE/surfels.ply")
    ap.add_argument("--tol-mm", type=float, default=1.0)
    ap.add_argument("--off-mm", type=float, default=1.0)
    args = ap.parse_args()
    scene = load_scene(f"data/scenes/{args.scene}", view_ids=None)
    K, T = scene.K, scene.world_to_cam
    truth = gt_depths_mm(*gt.read_mesh(f"data/synth/{args.scene}/gt/mesh.ply"), K, T, scene.width, scene.height)
    params = read_surfel_ply(args.surfels or f"data/surfels/{args.scene}/surfels.ply", scene.norm_to_world)
    rendered, _ = render_depths_mm(params, scene, T, K, scene.width, scene.height, "median", 0.5, "cpu", scene.masks)
    print("| view | other views seeing | share of pixels | in front | behind |")
    print("| --- | --- | --- | --- | --- |")
    for i in range(scene.num_views):
        ok = (truth[i] > 0) & (rendered[i] > 0)
        if scene.masks is not None:
            ok &= scene.masks[i]
        ys, xs = np.nonzero(ok)
        count = other_views_seeing(truth, K, T, i, ys, xs, args.tol_mm)
        err = rendered[i][ys, xs] - truth[i][ys, xs]
        for k in range(scene.num_views):
            m = count == k
            if m.any():
                print(f"| {scene.view_ids[i]} | {k} | {m.mean():.3f} | {np.mean(err[m] < -args.off_mm):.3f} | "
                      f"{np.mean(err[m] > args.off_mm):.3f} |")


if __name__ == "__main__":
    main()
