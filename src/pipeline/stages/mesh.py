"""``gcgs mesh``: trained surfels -> depth rendered at the input views (and optional virtual
views) -> TSDF mesh in world mm, cleaned (docs/mesh.md). Settings: params ``mesh``."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pipeline import atomic
from pipeline.config import MeshConfig, OptimizeConfig, load_params, section
from pipeline.data.dtu import load_scene
from pipeline.meshing import tsdf
from pipeline.meshing.surfels import mesh_from_surfels
from pipeline.optimize.surfels import read_surfel_ply
from pipeline.optimize.train import resolve_backend


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--surfels-dir", required=True, help="optimize stage output (surfels.ply)")
    p.add_argument("--out-dir", required=True, help="writes mesh.ply and mesh.json")
    p.add_argument("--depth", choices=("median", "expected"), default=None, help="default: mesh.depth")
    p.add_argument("--virtual-per-pair", type=int, default=None, help="default: mesh.virtual_per_pair")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    cfg = section(MeshConfig, "mesh", params, {"depth": args.depth, "virtual_per_pair": args.virtual_per_pair})
    backend = resolve_backend(section(OptimizeConfig, "optimize", params).backend)
    scene = load_scene(args.scene, view_ids=None)
    surfels = read_surfel_ply(Path(args.surfels_dir) / "surfels.ply", scene.norm_to_world)
    mesh, info = mesh_from_surfels(surfels, scene, cfg, backend)
    out = Path(args.out_dir)
    with atomic.atomic_dir(out) as tmp:
        tsdf.write_mesh(tmp / "mesh.ply", mesh)
        (tmp / "mesh.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")
    print(f"mesh: {info['triangles_kept']} triangles ({info['components_kept']} of {info['components_fused']} "
          f"components kept) from {info['views_input']} input + {info['views_virtual']} virtual views -> {out}",
          file=sys.stderr)
    warning = tsdf.cleaning_warning(info)
    if warning:
        print(f"gcgs mesh: warning: {out}: {warning}", file=sys.stderr)
    return 0
