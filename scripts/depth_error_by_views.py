"""Rendered depth error at the input views, split by how many of the other input views see
the surface there (docs/optimize.md, "The strips are the surface fewer than three views see").

For each input view of a synthetic scene, every pixel inside the mask where both the GT and
the surfels have depth: how many of the other input views see its GT point
(:func:`pipeline.evaluation.seen.views_seeing`, the rule of the Chamfer split). Prints,
per view and per count of other views, the share of the pixels and the shares rendered more
than ``--off-mm`` in front of / behind the GT.

    python scripts/depth_error_by_views.py synth_thin [--surfels data/surfels/synth_thin/surfels.ply]
"""
from __future__ import annotations

import argparse

import numpy as np

from pipeline import geometry
from pipeline.data.dtu import load_scene
from pipeline.evaluation import gt, seen
from pipeline.evaluation.depth_error import gt_depths_mm
from pipeline.meshing.surfels import render_depths_mm
from pipeline.surfels import read_surfel_ply


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--surfels", default=None, help="default: data/surfels/SCENE/surfels.ply")
    ap.add_argument("--off-mm", type=float, default=1.0)
    args = ap.parse_args()
    scene = load_scene(f"data/scenes/{args.scene}", view_ids=None)
    K, T = scene.K, scene.world_to_cam
    gt_mesh = gt.read_mesh(f"data/synth/{args.scene}/gt/mesh.ply")
    truth = gt_depths_mm(*gt_mesh, K, T, scene.width, scene.height)
    views = [seen.InputView(K[i], T[i], scene.width, scene.height) for i in range(scene.num_views)]
    params = read_surfel_ply(args.surfels or f"data/surfels/{args.scene}/surfels.ply", scene.norm_to_world)
    rendered, _ = render_depths_mm(params, scene, T, K, scene.width, scene.height, "median", 0.5, "cpu", scene.masks)
    print("| view | other views seeing | share of pixels | in front | behind |")
    print("| --- | --- | --- | --- | --- |")
    for i in range(scene.num_views):
        ok = (truth[i] > 0) & (rendered[i] > 0)
        if scene.masks is not None:
            ok &= scene.masks[i]
        ys, xs = np.nonzero(ok)
        points = geometry.backproject_depth(K[i], T[i], truth[i])[ys, xs]
        count = seen.views_seeing(points, *gt_mesh, [v for j, v in enumerate(views) if j != i])
        err = rendered[i][ys, xs] - truth[i][ys, xs]
        for k in range(scene.num_views):
            m = count == k
            if m.any():
                print(f"| {scene.view_ids[i]} | {k} | {m.mean():.3f} | {np.mean(err[m] < -args.off_mm):.3f} | "
                      f"{np.mean(err[m] > args.off_mm):.3f} |")


if __name__ == "__main__":
    main()
