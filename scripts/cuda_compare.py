"""The CPU half of the cuda backend's check: what the cuda backend's surfel-centre depth
does at the input views, against the cpu backend's ray-splat intersection depth of the same
surfels and, on a synthetic scene, against the ground truth (docs/rasterizer.md, "The cuda
backend, run").

    python scripts/cuda_compare.py SCENE RENDERS.npz [--gt data/synth/SCENE/gt/mesh.ply]

RENDERS.npz is one of ``scripts/cuda_check.py``'s: keys ``SET/depth_median_mm``,
``SET/alpha``, ... for the surfel sets ``cuda_trained`` and ``cpu_trained``; the surfels of
a set are read from ``--surfels SET=PLY``. Prints a JSON object.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from pipeline.data.dtu import load_scene
from pipeline.evaluation import gt
from pipeline.evaluation.depth_error import gt_depths_mm
from pipeline.meshing.surfels import render_depths_mm
from pipeline.surfels import read_surfel_ply


def _stats(d: np.ndarray) -> dict:
    d = np.abs(d)
    return {"pixels": int(d.size), "mean_mm": round(float(d.mean()), 4), "median_mm": round(float(np.median(d)), 4),
            "p99_mm": round(float(np.percentile(d, 99)), 4)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("renders")
    ap.add_argument("--surfels", nargs="+", required=True, help="SET=PLY for each surfel set to compare")
    ap.add_argument("--gt", default=None, help="GT mesh (world mm) of a synthetic scene")
    args = ap.parse_args()
    scene = load_scene(f"data/scenes/{args.scene}", view_ids=None)
    renders = np.load(args.renders)
    truth = None
    if args.gt:
        truth = gt_depths_mm(*gt.read_mesh(args.gt), scene.K, scene.world_to_cam, scene.width, scene.height)
    report: dict = {}
    for item in args.surfels:
        name, ply = item.split("=", 1)
        params = read_surfel_ply(ply, scene.norm_to_world)
        cpu_depth, _ = render_depths_mm(params, scene, scene.world_to_cam, scene.K, scene.width, scene.height,
                                        "median", 0.5, "cpu")
        cuda_depth = renders[f"{name}/depth_median_mm"].astype(np.float64)
        both = (cpu_depth > 0) & (cuda_depth > 0) & (renders[f"{name}/alpha"] > 0.5)
        entry = {"cuda_minus_cpu_median_depth": _stats(cuda_depth[both] - cpu_depth[both]),
                 "cuda_signed_median_mm": round(float(np.median(cuda_depth[both] - cpu_depth[both])), 4)}
        if truth is not None:
            ok = both & (truth > 0)
            entry["cpu_vs_gt"] = _stats(cpu_depth[ok] - truth[ok])
            entry["cuda_vs_gt"] = _stats(cuda_depth[ok] - truth[ok])
        report[name] = entry
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
