"""``gcgs variant-score SCENE VARIANT``: the scoring half of an ablation cell (Table II):
the variant's trained surfels meshed and scored (params ``ablation``, docs/optimize.md)."""
from __future__ import annotations

import argparse

from pipeline.config.data import DataConfig
from pipeline.config.params import load_params, section
from pipeline.config.scenes import scene_entry
from pipeline.config.variants import init_sources
from pipeline.runs.variant_score import score_variant


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", help="scene name (a key of params `scenes`)")
    p.add_argument("variant", help="variant name (a key of params `ablation.variants`)")
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--init-dir", required=True, help="init stage output (its depth maps merge into the mesh)")
    p.add_argument("--baseline-dir", required=True, help="the baseline stage's output (sfm/ and random/ clouds)")
    p.add_argument("--out-dir", required=True, help="reads surfels/, writes mesh/")
    p.add_argument("--report", required=True, help="metrics JSON (the training time read from beside it, .train.json)")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    entry = scene_entry(params, args.name)
    m = score_variant(args.name, args.variant, params, args.scene, entry.src, entry.gt,
                      init_sources(args.init_dir, args.baseline_dir), args.out_dir, args.report,
                      section(DataConfig, "data", params).views)
    print(f"variant {args.variant} on {args.name}: {m.chamfer.overall_mm if m.chamfer else None} mm overall -> {args.report}")
    return 0
