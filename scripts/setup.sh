#!/usr/bin/env bash
# Idempotent set-up: a virtual environment in .venv with the pinned dependencies.
# torch is installed first and pinned, so that no other package can pull a CUDA build.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
. .venv/bin/activate
stamp=.venv/.gcgs-installed
want=$(cat requirements.txt pyproject.toml | sha256sum | cut -c1-16)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  # pip warns about every absent mirror folder of this machine's index; keep the log readable.
  quiet() { "$@" 2>&1 | { grep -v "^WARNING: Location" || true; }; }
  quiet python -m pip install -q torch==2.13.0
  quiet python -m pip install -q -r requirements.txt
  quiet python -m pip install -q --no-deps -e .
  echo "$want" > "$stamp"
fi
