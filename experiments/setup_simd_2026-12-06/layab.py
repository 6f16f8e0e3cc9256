"""In one process, the patched code's render with its forward scratch as is, and with 25.6 MB
more at its end (the layout before the patch: the surfel table was carved there), alternated;
the backward's and forward's own seconds. Run with the patched tree on PYTHONPATH, KEEP=1."""
import sys, time, statistics, cProfile, pstats
from pipeline import heap; heap.keep_freed_memory()
sys.argv = ["x"]
from pathlib import Path
exec((Path(__file__).with_name("harness.py")).read_text().split("mode = sys.argv[1]")[0])
import numpy as np
from pipeline.rasterizer import simd, cpu
from pipeline.benchmarks import rasterizer as B
MODE = {"m": "asis"}
orig_take = cpu.SCRATCH.take
def take(role, nbytes):
    if role == "simd-forward" and MODE["m"] == "pad":
        return orig_take("simd-forward-pad", nbytes + 200_000 * 128 + 64)
    return orig_take(role, nbytes)
orig_give = cpu.SCRATCH.give
cpu.SCRATCH.take = take
s, cam = case(800, 600, 200_000, 3)
_, cot = run(s, cam, "auto")
res = {m: [] for m in ("asis", "pad")}
for r in range(6):
    for m in (["asis", "pad"] if r % 2 == 0 else ["pad", "asis"]):
        MODE["m"] = m
        prof = cProfile.Profile(); prof.enable()
        for _ in range(3): run(s, cam, "auto", cot)
        prof.disable()
        own = B.kernel_seconds(pstats.Stats(prof))
        res[m].append((own["simd.backward_all"] / 3, own["simd.forward_all"] / 3))
for m, v in res.items():
    print(m, "bwd %.4f fwd %.4f" % tuple(statistics.median(x[i] for x in v) for i in range(2)), [round(x[0], 4) for x in v])
