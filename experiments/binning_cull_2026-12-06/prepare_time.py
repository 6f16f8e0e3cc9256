"""prepare_time.py: the set-up and binning of the benchmark's scene (800x600 / 200k) through
the simd and the numba backends, one and two threads, medians of 15. Run it with the
repository root as working folder and PYTHONPATH at the tree to time (this tree's src, or a
`git archive` of another commit's), alternating the trees."""
import statistics
import sys
import time
from pathlib import Path

import numba

sys.argv = ["x", "none"]
exec(open(Path(__file__).resolve().parent.parent / "setup_simd_2026-12-06" / "harness.py").read().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import cpu, simd

s, cam = case(800, 600, 200000, 3)
runs = {"simd": lambda: simd.prepare(s.means, s.quats, s.scales, s.opacities, s.features, cam),
        "numba": lambda: cpu.prepare(s.means, s.quats, s.scales, s.opacities, cam)}
for name, f in runs.items():
    f()
    for threads in (1, 2):
        numba.set_num_threads(threads)
        ts = []
        for _ in range(15):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        print(f"{simd.__file__}: {name} prepare, {threads} thread(s): {statistics.median(ts) * 1e3:.2f} ms")
