"""``gcgs baseline-report``: combine the per-scene reports of ``gcgs baseline``
(``REPORTS/SCENE.json`` for every scene in params ``scenes``) into one Markdown table."""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.params import load_params
from pipeline.reports.baseline_table import markdown


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--reports-dir", default="reports/baseline", help="folder of the per-scene SCENE.json")
    p.add_argument("--out", default="reports/baseline.md", help="Markdown file to write")
    p.add_argument("--params", default=None, help="params.yaml (scene names; default: ./params.yaml)")
    p.add_argument("--note", action="append", default=[], help="a line for the report's notes")


def run(args: argparse.Namespace) -> int:
    names = list(load_params(args.params).get("scenes") or {})
    if not names:
        raise ValueError("params `scenes` is empty: no baseline to combine")
    atomic.check_output_file(args.out, inputs=(args.reports_dir,))
    reports = {}
    for name in names:
        path = Path(args.reports_dir) / f"{name}.json"
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no baseline report for scene {name} (run `gcgs baseline --scene {name}`)")
        reports[name] = json.loads(path.read_text())
    atomic.write_text(args.out, markdown(reports, args.note))
    print(f"[baseline-report] {len(reports)} scene(s) -> {args.out}")
    return 0
