"""perf_lines.py: the benchmark's scene rendered through the simd kernels built with -g (same
code, line tables), for `perf record -p PID` once /tmp/perf_lines.ready exists, and
`perf annotate -l`; see the README."""
import sys, time, tempfile, os
from pathlib import Path
import numpy as np, torch
from pipeline import heap; heap.keep_freed_memory()
sys.argv = ["x", "none"]
exec(open(__import__("pathlib").Path(__file__).resolve().parent.parent / "setup_simd_2026-12-06" / "harness.py").read().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import simd
lib = simd.load(simd.build(simd._compiler(), simd.FLAGS + ("-g",), Path(tempfile.gettempdir()) / "perfg"))
simd._state["kernels"] = {n: simd._CFunction(getattr(lib, n), a) for n, a in simd._FUNCTIONS.items()}
s, cam = case(800, 600, 200000, 3)
_, cot = run(s, cam, "simd")
open("/tmp/perf_lines.ready", "w").write("1")
for _ in range(int(os.environ.get("REPS", "25"))):
    run(s, cam, "simd", cot)
