"""``gcgs variant-train SCENE VARIANT``: the training half of an ablation cell (Table II):
the variant's surfels and its training time (params ``ablation``, docs/optimize.md)."""
from __future__ import annotations

import argparse

from pipeline.config.params import load_params
from pipeline.config.variants import init_sources
from pipeline.runs.variant_train import train_variant


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="scene name (a key of params `scenes`)")
    p.add_argument("variant", help="variant name (a key of params `ablation.variants`)")
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--init-dir", required=True, help="init stage output (the mvs cloud)")
    p.add_argument("--baseline-dir", required=True, help="the baseline stage's output (sfm/ and random/ clouds)")
    p.add_argument("--priors-dir", required=True, help="priors stage output")
    p.add_argument("--out-dir", required=True, help="writes surfels/")
    p.add_argument("--report", required=True, help="the cell's metrics JSON; the training time goes beside it "
                   "(.train.json)")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    train_variant(args.variant, load_params(args.params), args.scene, init_sources(args.init_dir, args.baseline_dir),
                  args.priors_dir, args.out_dir, args.report)
    print(f"variant {args.variant} on {args.name}: trained -> {args.out_dir}/surfels")
    return 0
