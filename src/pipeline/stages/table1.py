"""``gcgs table1``: Table I (overall Chamfer per scene, measured here next to published
figures; held-out scores of the scans without ground truth) -> Markdown and CSV, for the
scenes of params ``scenes`` (:mod:`pipeline.reports.table1`)."""
from __future__ import annotations

import argparse

from pipeline import atomic
from pipeline.config.params import load_params
from pipeline.measure import provenance
from pipeline.reports.table1 import build_table1, csv_text, markdown


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--metrics-dir", default="reports/metrics", help="folder of the method's SCENE.json (gcgs score)")
    p.add_argument("--baseline-dir", default="reports/baseline", help="folder of the baseline's SCENE.json")
    p.add_argument("--published", default="data/published/dtu_3view_table1.csv", help="published figures (CSV)")
    p.add_argument("--out-md", default="reports/table1.md", help="Markdown table to write")
    p.add_argument("--out-csv", default="reports/table1.csv", help="CSV table to write")
    p.add_argument("--params", default=None, help="params.yaml (scenes; default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    scenes = load_params(args.params).get("scenes") or {}
    commit = provenance()["commit"]
    # Both texts are built before either file is written: bad input leaves no half output.
    for out in (args.out_md, args.out_csv):
        atomic.check_output_file(out, inputs=(args.metrics_dir, args.baseline_dir, args.published))
    table = build_table1(scenes, args.metrics_dir, args.baseline_dir, args.published, commit)
    md, csv = markdown(table, commit), csv_text(table)
    atomic.write_text(args.out_md, md)
    atomic.write_text(args.out_csv, csv)
    print(f"[table1] {len(table.scenes_synthetic) + len(table.scenes_dtu)} scene column(s), "
          f"{len(table.heldout)} held-out scene(s) -> {args.out_md}, {args.out_csv}")
    return 0
