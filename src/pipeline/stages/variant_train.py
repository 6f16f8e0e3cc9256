"""``gcgs variant-train SCENE VARIANT``: the training half of an ablation cell (Table II):
the variant's surfels and its training time (params ``ablation``, docs/optimize.md)."""
from __future__ import annotations

import argparse

from pipeline.config.params import load_params
from pipeline.config.variants import init_sources
from pipeline.runs.variant_train import train_variant
from pipeline.stages.cell_args import add_cell_arguments


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_cell_arguments(p, priors=True, out_help="writes surfels/",
                       report_help="the cell's metrics JSON; the training time goes beside it (.train.json)")


def run(args: argparse.Namespace) -> int:
    train_variant(args.variant, load_params(args.params), args.scene, init_sources(args.init_dir, args.baseline_dir),
                  args.priors_dir, args.out_dir, args.report)
    print(f"variant {args.variant} on {args.name}: trained -> {args.out_dir}/surfels")
    return 0
