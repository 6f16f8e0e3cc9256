"""``gcgs report-index``: ``reports/index.md``, the page that shows the tables, the
speed-accuracy plot, each configured scene's figures, settings, picture and training curves
(:mod:`pipeline.reports.index`)."""
from __future__ import annotations

import argparse
from pathlib import Path

from pipeline import atomic
from pipeline.config.params import load_params
from pipeline.measure import provenance
from pipeline.reports.index import index_markdown


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--reports-dir", default="reports", help="the reports folder (index.md links inside it)")
    p.add_argument("--out", default=None, help="Markdown file to write (default: REPORTS_DIR/index.md)")
    p.add_argument("--params", default=None, help="params.yaml (scenes; default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    scenes = load_params(args.params).get("scenes") or {}
    out = Path(args.out or Path(args.reports_dir) / "index.md")
    atomic.write_text(out, index_markdown(args.reports_dir, scenes, provenance()["commit"]))
    print(f"[report-index] {len(scenes)} scene(s) -> {out}")
    return 0
