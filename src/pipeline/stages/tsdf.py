"""``gcgs tsdf``: TSDF-fuse an init folder's depth maps (``depth/*.npz``) into a cleaned
mesh (world mm) with :func:`pipeline.meshing.tsdf.mesh_from_init`: the classical baseline
mesh. Sizes and the component-keeping rule come from params ``mesh``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from pipeline import atomic
from pipeline.config.mesh import MeshConfig
from pipeline.config.params import load_params, section
from pipeline.measure import peak_rss_mb
from pipeline.meshing import tsdf


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--init-dir", required=True, help="output folder of `gcgs init` (with depth/)")
    p.add_argument("--scene", required=True, help="the scene folder (colours, scale)")
    p.add_argument("--out", required=True, help="mesh PLY to write (world mm)")
    p.add_argument("--voxel-norm", type=float, default=None, help="voxel, unit-sphere radii (default: mesh.voxel_norm)")
    p.add_argument("--trunc-norm", type=float, default=None,
                   help="SDF truncation, unit-sphere radii (default: mesh.trunc_norm)")
    p.add_argument("--min-component-fraction", type=float, default=None,
                   help="keep components with at least this fraction of the largest one's triangles "
                        "(default: mesh.min_component_fraction)")
    p.add_argument("--params", default=None, help="params.yaml to read `mesh` from (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    atomic.check_output_file(args.out, inputs=(args.init_dir, args.scene))
    t0 = time.perf_counter()
    cfg = section(MeshConfig, "mesh", load_params(args.params),
                  {"voxel_norm": args.voxel_norm, "trunc_norm": args.trunc_norm,
                   "min_component_fraction": args.min_component_fraction})
    mesh, info = tsdf.mesh_from_init(args.init_dir, args.scene, cfg)
    tsdf.write_mesh(args.out, mesh)
    print(f"tsdf: fused {info['triangles_fused']} triangles in {info['components_fused']} components, kept "
          f"{info['triangles_kept']} in {info['components_kept']} -> {args.out}", file=sys.stderr)
    warning = tsdf.cleaning_warning(info)
    if warning:
        print(f"gcgs tsdf: warning: {args.out}: {warning}", file=sys.stderr)
    info.update(time_s=round(time.perf_counter() - t0, 2), peak_rss_mb=peak_rss_mb())
    print(json.dumps(info))
    return 0
