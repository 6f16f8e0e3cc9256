"""``gcgs mesh``: trained surfels -> depth rendered at the input views (and optional virtual
views) -> TSDF mesh in world mm, cleaned (docs/mesh.md). Settings: params ``mesh``."""
from __future__ import annotations

import argparse
import sys

from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.meshing import tsdf
from pipeline.rasterizer import resolve_backend
from pipeline.runs.mesh import mesh_surfels_dir


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--surfels-dir", required=True, help="optimize stage output (surfels.ply)")
    p.add_argument("--out-dir", required=True, help="writes mesh.ply and mesh.json")
    p.add_argument("--init-dir", default=None,
                   help="init stage output: its depth maps, merged in where mesh.init_depth_rel_tol > 0")
    p.add_argument("--depth", choices=("median", "expected"), default=None, help="default: mesh.depth")
    p.add_argument("--virtual-per-pair", type=int, default=None, help="default: mesh.virtual_per_pair")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    cfg = section(MeshConfig, "mesh", params, {"depth": args.depth, "virtual_per_pair": args.virtual_per_pair})
    backend = resolve_backend(section(OptimizeConfig, "optimize", params).backend)
    out = args.out_dir
    info = mesh_surfels_dir(args.scene, args.surfels_dir, out, cfg, backend, args.init_dir)
    print(f"mesh: {info['triangles_kept']} triangles ({info['components_kept']} of {info['components_fused']} "
          f"components kept) from {info['views_input']} input + {info['views_virtual']} virtual views -> {out}",
          file=sys.stderr)
    warning = tsdf.cleaning_warning(info)
    if warning:
        print(f"gcgs mesh: warning: {out}: {warning}", file=sys.stderr)
    return 0
