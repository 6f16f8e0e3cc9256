#!/usr/bin/env bash
# Set up (if needed) and run the pipeline on the bundled data with DVC.
#   bash scripts/main.sh          the main job: the method on every scene (init -> priors ->
#                                 optimize -> mesh -> evaluate), the classical baseline and
#                                 Table I
#   bash scripts/main.sh --all    everything in dvc.yaml: also the ablation (Table II), the
#                                 renders and reports/index.md
#   bash scripts/main.sh STAGE..  those stages (and what they depend on)
# How long each takes, measured: README.md, "Set up and run".
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
if [ $# -eq 0 ]; then
    set -- table1 baseline-report
elif [ "$1" = "--all" ]; then
    shift
fi
dvc repro "$@"
