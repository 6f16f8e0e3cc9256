"""``gcgs variant SCENE VARIANT``: one whole cell of the ablation (Table II) or of a sweep:
the variant trained, meshed and scored on one scene (params ``ablation``, docs/optimize.md).
DVC runs the halves as ``gcgs variant-train`` and ``gcgs variant-score``."""
from __future__ import annotations

import argparse

from pipeline.config.data import DataConfig
from pipeline.data import dtu
from pipeline.config.params import load_params, section
from pipeline.config.scenes import scene_entry
from pipeline.config.variants import init_sources
from pipeline.runs.variant import run_variant
from pipeline.stages.cell_args import add_cell_arguments


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_cell_arguments(p, priors=True, out_help="writes surfels/ and mesh/",
                       report_help="metrics JSON (training time beside it, .train.json)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    entry = scene_entry(params, args.name)
    m = run_variant(args.name, args.variant, params, args.scene, entry.src, entry.gt,
                    init_sources(args.init_dir, args.baseline_dir), args.priors_dir, args.out_dir, args.report,
                    dtu.prepared_views(args.scene) or section(DataConfig, "data", params).views)
    print(f"variant {args.variant} on {args.name}: {m.chamfer.overall_mm if m.chamfer else None} mm overall -> {args.report}")
    return 0
