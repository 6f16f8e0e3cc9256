#!/usr/bin/env bash
# Set up (if needed) and run the whole pipeline on the bundled data with DVC.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
dvc repro "$@"
