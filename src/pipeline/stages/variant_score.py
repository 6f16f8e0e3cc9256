"""``gcgs variant-score SCENE VARIANT``: the scoring half of an ablation cell (Table II):
the variant's trained surfels meshed and scored (params ``ablation``, docs/optimize.md)."""
from __future__ import annotations

import argparse

from pipeline.config.data import DataConfig
from pipeline.data import dtu
from pipeline.config.params import load_params, section
from pipeline.config.scenes import scene_entry
from pipeline.config.variants import init_sources
from pipeline.runs.variant_score import score_variant
from pipeline.stages.cell_args import add_cell_arguments


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_cell_arguments(p, priors=False, out_help="reads surfels/, writes mesh/",
                       report_help="metrics JSON (the training time read from beside it, .train.json)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    entry = scene_entry(params, args.name)
    m = score_variant(args.name, args.variant, params, args.scene, entry.src, entry.gt,
                      init_sources(args.init_dir, args.baseline_dir), args.out_dir, args.report,
                      dtu.prepared_views(args.scene) or section(DataConfig, "data", params).views)
    print(f"variant {args.variant} on {args.name}: {m.chamfer.overall_mm if m.chamfer else None} mm overall -> {args.report}")
    return 0
