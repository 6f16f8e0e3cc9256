"""``gcgs render-scene``: one scene's pictures for the report (:mod:`pipeline.reports.renders`):
input view, surfels' colour and normal, mesh -> ``reports/renders/SCENE.png``; with ``--src``
and ``--heldout-out``, the mesh's silhouette against the masks of held-out views ->
``reports/renders/SCENE_heldout.png``."""
from __future__ import annotations

import argparse

from pipeline import atomic
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.errors import ConfigError
from pipeline.rasterizer import resolve_backend
from pipeline.reports.renders import HELDOUT_VIEWS, PANEL_WIDTH, render_scene


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--surfels", required=True, help="trained surfels (optimize stage: surfels.ply)")
    p.add_argument("--mesh", required=True, help="extracted mesh, world mm (mesh stage: mesh.ply)")
    p.add_argument("--out", required=True, help="PNG to write")
    p.add_argument("--panel-width", type=int, default=PANEL_WIDTH, help="width of each panel, px")
    p.add_argument("--src", default=None,
                   help="the scan the scene was prepared from: its held-out views (SRC/heldout/, else SRC/image/ "
                        "less the scene's views), with masks, as the score stage reads them")
    p.add_argument("--heldout-out", default=None, help="PNG of the mesh's silhouette at held-out views (needs --src)")
    p.add_argument("--heldout-views", type=int, default=HELDOUT_VIEWS, help="how many held-out views to show")
    p.add_argument("--params", default=None, help="params.yaml (optimize.background, optimize.backend)")


def run(args: argparse.Namespace) -> int:
    if (args.src is None) != (args.heldout_out is None):
        raise ConfigError("--src and --heldout-out go together (the held-out picture needs the scan's held-out views)")
    if args.panel_width < 1 or args.heldout_views < 1:
        raise ConfigError(f"--panel-width ({args.panel_width}) and --heldout-views ({args.heldout_views}) "
                          "must be positive")
    for out in (args.out, args.heldout_out):
        if out is not None:
            atomic.check_output_file(out, inputs=(args.scene, args.surfels, args.mesh, args.src))
    opt = section(OptimizeConfig, "optimize", load_params(args.params))
    render_scene(args.scene, args.surfels, args.mesh, args.out, args.panel_width, opt.background,
                 resolve_backend(opt.backend), args.src, args.heldout_out, args.heldout_views)
    return 0
