"""``gcgs render-scene``: one scene's picture for the report (input view, surfels' colour and
normal, mesh; :mod:`pipeline.reports.renders`) -> ``reports/renders/SCENE.png``."""
from __future__ import annotations

import argparse

from pipeline.config import OptimizeConfig, load_params, section
from pipeline.reports.renders import PANEL_WIDTH, scene_panels, write_png
from pipeline.rasterizer import resolve_backend


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--surfels", required=True, help="trained surfels (optimize stage: surfels.ply)")
    p.add_argument("--mesh", required=True, help="extracted mesh, world mm (mesh stage: mesh.ply)")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--panel-width", type=int, default=PANEL_WIDTH, help="width of each of the four panels, px")
    p.add_argument("--params", default=None, help="params.yaml (optimize.background, optimize.backend)")


def run(args: argparse.Namespace) -> int:
    opt = section(OptimizeConfig, "optimize", load_params(args.params))
    rgb = scene_panels(args.scene, args.surfels, args.mesh, args.panel_width, opt.background,
                       resolve_backend(opt.backend))
    write_png(args.out, rgb)
    print(f"[render-scene] {args.scene}: {rgb.shape[1]}x{rgb.shape[0]} -> {args.out}")
    return 0
