"""The command-line arguments an ablation cell's commands share (``gcgs variant``,
``gcgs variant-train``, ``gcgs variant-score``): which cell, and where its inputs and
outputs are. Not a stage itself."""
from __future__ import annotations

import argparse


def add_cell_arguments(p: argparse.ArgumentParser, *, priors: bool, out_help: str, report_help: str) -> None:
    p.add_argument("name", help="scene name (a key of params `scenes`)")
    p.add_argument("variant", help="variant name (a key of params `ablation.variants`)")
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--init-dir", required=True, help="init stage output (the mvs cloud and depth maps)")
    p.add_argument("--baseline-dir", required=True, help="the baseline stage's output (sfm/ and random/ clouds)")
    if priors:
        p.add_argument("--priors-dir", required=True, help="priors stage output")
    p.add_argument("--out-dir", required=True, help=out_help)
    p.add_argument("--report", required=True, help=report_help)
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")
