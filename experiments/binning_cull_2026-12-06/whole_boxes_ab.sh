#!/usr/bin/env bash
# whole_boxes_ab.sh [ROUNDS]: the render with the culled tile lists against the whole boxes'
# lists, alternated in one process (../wrapper_setup_2026-12-06/soab.py), bit for bit checked.
# The whole-box variant is _simd.cpp with tile_reached answering yes at once (the compiler then
# drops the test). Run from the repository root with the venv on.
set -euo pipefail
tmp=$(mktemp -d)
cp src/pipeline/rasterizer/_simd.cpp "$tmp/culled.cpp"
python - "$tmp" <<'PY'
import sys
d = sys.argv[1]
s = open(f"{d}/culled.cpp").read()
head = "NO_CONTRACT inline bool tile_reached(const TileConic &c, double xa, double xb, double ya, double yb) {\n"
assert head in s
open(f"{d}/whole.cpp", "w").write(s.replace(head, head + "    if (xa > -1) return true;\n"))
PY
python experiments/wrapper_setup_2026-12-06/soab.py "${1:-16}" "$tmp/whole.cpp" "$tmp/culled.cpp"
