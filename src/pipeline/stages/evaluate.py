"""``gcgs evaluate``: DTU Chamfer distance (accuracy, completeness, overall; mm) of a mesh.

Follows the public DTU evaluation script (see :mod:`pipeline.evaluation.dtu_eval` and
docs/evaluation.md). The mesh must be in the DTU world frame, in millimetres.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from pipeline import atomic
from pipeline.config.data import DataConfig
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.params import load_params, section
from pipeline.data import dtu
from pipeline.errors import InputError, MissingInputError
from pipeline.evaluation import coverage, dtu_eval, gt


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mesh", required=True, help="mesh to evaluate (PLY/OBJ, world frame, mm)")
    p.add_argument("--scene", required=True, help="DTU-layout scene folder (cameras and masks for culling)")
    p.add_argument("--gt", default=None, help="ground-truth root in the DTU 'MVS Data' layout (default: SCENE/gt)")
    p.add_argument("--scan-id", type=int, default=None,
                   help="scan number of the GT files (default: scene.json, else the only one in the GT folder)")
    p.add_argument("--cull", choices=("input", "all", "none"), default=None,
                   help="mask culling views (default: params evaluate.cull_views)")
    p.add_argument("--views", type=int, nargs="+", default=None,
                   help="input views (default: those the scene was prepared with, its scene.json `views`; "
                        "for a scene that records none, params data.views)")
    p.add_argument("--seed", type=int, default=0, help="seed of the downsampling order")
    p.add_argument("--params", default=None, help="params.yaml to read `evaluate` and `data` from")
    p.add_argument("--accuracy-by-mesh", default=None, metavar="REFERENCE",
                   help="also split the accuracy by a reference mesh (world mm): on the surface within "
                        "--within-mm of it and on the surface only this mesh has (docs/evaluation.md)")
    p.add_argument("--within-mm", type=float, default=1.0, help="distance that counts as the reference's surface")
    p.add_argument("--out", required=True, help="metrics JSON to write")


def run(args: argparse.Namespace) -> int:
    atomic.check_output_file(args.out, inputs=(args.mesh, args.accuracy_by_mesh, args.scene, args.gt))
    if not (args.within_mm > 0 and math.isfinite(args.within_mm)):
        raise InputError(f"--within-mm must be a positive distance in mm, got {args.within_mm}")
    params = load_params(args.params)
    cfg = section(EvaluateConfig, "evaluate", params, {"cull_views": args.cull})

    scene = Path(args.scene)
    if not scene.is_dir():
        raise MissingInputError(f"{scene}: scene folder not found")
    views = section(DataConfig, "data", params, {"views": args.views or dtu.prepared_views(scene)}).views
    scan_id = args.scan_id if args.scan_id is not None else dtu.read_meta(scene).get("scan_id")
    ground = gt.read_ground_truth(args.gt or scene / "gt", scan_id)
    print(f"[evaluate] GT scan {ground.scan_id}: {len(ground.points_mm)} points, ObsMask {ground.obs_mask.shape} "
          f"at {ground.res_mm} mm ({ground.root})", flush=True)
    cull = dtu_eval.load_cull_views(scene, cfg.cull_views, views)
    vertices, triangles = gt.read_mesh(args.mesh)
    metrics = dtu_eval.evaluate_mesh(vertices, triangles, ground, cfg, views=cull, seed=args.seed,
                                     log=lambda m: print(m, flush=True), name=str(args.mesh))
    metrics.update(mesh=str(args.mesh), scene=str(scene), gt=str(ground.root))
    if args.accuracy_by_mesh:
        metrics["accuracy_by_reference"] = {"reference": str(args.accuracy_by_mesh), **coverage.accuracy_by_reference(
            vertices, triangles, *gt.read_mesh(args.accuracy_by_mesh), ground, cfg, views=cull, seed=args.seed,
            within_mm=args.within_mm, log=lambda m: print(m, flush=True))}
    dtu_eval.write_metrics(args.out, metrics)
    print(f"[evaluate] wrote {args.out}", flush=True)
    if not metrics["valid"]:
        print(f"gcgs evaluate: warning: metrics undefined ({'; '.join(metrics['problems'])}); "
              "written as null", file=sys.stderr)
    return 0
