"""Run the speed-accuracy sweep (params ``ablation.speed_accuracy``) and write
``reports/speed_accuracy.csv`` and ``reports/speed_accuracy.png`` (docs/speed_accuracy.md).

Each cell is ``gcgs variant SCENE CELL`` (one variant trained, meshed and scored on one
scene) in its own process; its metrics go to ``reports/speed_accuracy/SCENE/CELL.json``.
Cells whose report exists are kept (the sweep resumes); ``--force`` reruns them. The
cells run one after the other so that their times compare; a launcher spreads them out
(docs/sweeps.md). A run interrupted inside a cell resumes from its checkpoint, and the
cell's times add those of the earlier runs. Usage: ``python scripts/speed_accuracy.py
[--only CELL ...] [--scenes SCENE ...] [--force]``.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

from pipeline.config.ablation import AblationConfig
from pipeline.config.params import load_params, section
from pipeline.evaluation.record import SceneMetrics
from pipeline.measure import provenance
from pipeline.reports.speed_accuracy import collect_cells, write_report

REPORTS = Path("reports/speed_accuracy")
# Cells whose settings are a preset of conf/optimize (tests/test_variants.py keeps them equal).
PRESET_CELLS = {
    "full": "fast (default)", "sa_it150": "quick", "sa_it1000": "balanced", "sa_it2000": "long", "sa_paper": "paper"
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="*", default=None, help="run only these cells")
    ap.add_argument("--scenes", nargs="*", default=None, help="run cells only on these scenes")
    ap.add_argument("--force", action="store_true", help="rerun cells whose report exists")
    ap.add_argument("--report-only", action="store_true", help="only rebuild the CSV and plot")
    ap.add_argument("--inputs", default="data", help="folder holding scenes/, init/, priors/, baseline/ of each "
                    "scene (default: data; a copy keeps the sweep apart from a running dvc repro)")
    args = ap.parse_args()
    sweep = section(AblationConfig, "ablation", load_params()).speed_accuracy
    for scene in sweep.scenes:
        for cell in sweep.cells:
            report = REPORTS / scene / f"{cell}.json"
            skip = (args.only is not None and cell not in args.only) or (args.scenes is not None and scene not in args.scenes)
            if args.report_only or skip or (report.is_file() and not args.force):
                continue
            env = dict(os.environ, OMP_WAIT_POLICY="PASSIVE")
            src = args.inputs
            cmd = ["gcgs", "variant", scene, cell, "--scene", f"{src}/scenes/{scene}", "--init-dir", f"{src}/init/{scene}",
                   "--baseline-dir", f"{src}/baseline/{scene}", "--priors-dir", f"{src}/priors/{scene}",
                   "--out-dir", f"data/speed_accuracy/{cell}/{scene}", "--report", str(report)]
            before = provenance()
            print(f"[sweep] {scene} {cell}: {' '.join(cmd)}", flush=True)
            subprocess.run(cmd, check=True, env=env)
            metrics = SceneMetrics.read(report)
            dataclasses.replace(metrics, provenance={**before, "load_average_1min_after": round(os.getloadavg()[0], 2)}
                                ).write(report)
    rows = collect_cells(REPORTS, sweep.scenes, sweep.cells)
    write_report(rows, Path("reports/speed_accuracy.csv"), Path("reports/speed_accuracy.png"), labels=PRESET_CELLS)
    print(f"[sweep] {len(rows)} cells -> reports/speed_accuracy.csv, reports/speed_accuracy.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
