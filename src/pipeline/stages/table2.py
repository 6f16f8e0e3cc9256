"""``gcgs table2``: Table II (the ablation on the synthetic suite) -> Markdown and CSV
(:mod:`pipeline.reports.table2`)."""
from __future__ import annotations

import argparse

from pipeline import atomic
from pipeline.config.ablation import AblationConfig
from pipeline.config.params import load_params, section
from pipeline.config.synth import SynthConfig
from pipeline.measure import provenance
from pipeline.reports.table2 import build_table2, csv_text, markdown, read_published_ablation


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--metrics-dir", default="reports/metrics", help="the full method's SCENE.json")
    p.add_argument("--variants-dir", default="reports/variants", help="VARIANT/SCENE.json of the variants")
    p.add_argument("--baseline-dir", default="reports/baseline", help="the classical baseline's SCENE.json")
    p.add_argument("--limit-dir", default="reports/limit", help="the 3-view limit's SCENE.json")
    p.add_argument("--published", default="data/published/gcgs_table2_ablation.csv",
                   help="the paper's Table II (published figures, shown apart)")
    p.add_argument("--out-md", default="reports/table2.md")
    p.add_argument("--out-csv", default="reports/table2.csv")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    ablation = section(AblationConfig, "ablation", params)
    scenes = section(SynthConfig, "synth", params).scenes
    for out in (args.out_md, args.out_csv):
        atomic.check_output_file(out, inputs=(args.metrics_dir, args.variants_dir, args.baseline_dir, args.limit_dir,
                                              args.published))
    rows = build_table2(params, scenes, ablation.run, ablation.variants, args.metrics_dir, args.variants_dir,
                        args.baseline_dir, args.limit_dir)
    md = markdown(rows, scenes, provenance()["commit"], read_published_ablation(args.published))
    text = csv_text(rows, scenes)
    atomic.write_text(args.out_md, md)
    atomic.write_text(args.out_csv, text)
    print(f"[table2] {len(rows)} rows x {len(scenes)} scenes -> {args.out_md}, {args.out_csv}")
    return 0
