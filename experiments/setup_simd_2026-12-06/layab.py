"""In one process, the patched code's render with its forward scratch as is, and with 25.6 MB
more at its end (the layout before the patch: the surfel table was carved there), each
variant with its own pool of scratch buffers, alternated; the backward's and forward's own
seconds. Run with the patched tree on PYTHONPATH, KEEP=1."""
import sys, statistics, cProfile, pstats
from pathlib import Path
from pipeline import heap; heap.keep_freed_memory()
ROUNDS = int(sys.argv[1]) if len(sys.argv) > 1 else 6
sys.argv = ["x"]
exec((Path(__file__).with_name("harness.py")).read_text().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import cpu
from pipeline.benchmarks import rasterizer as B
PAD = 200_000 * 128 + 64
MODE = {"m": "asis"}
take0, give0 = cpu.SCRATCH.take, cpu.SCRATCH.give
def take(role, nbytes):
    if role == "simd-forward" and MODE["m"] == "pad":
        buf = take0("simd-forward-pad", nbytes + PAD)
        pads.add(buf.ctypes.data)
        return buf
    return take0(role, nbytes)
def give(role, buf):
    give0("simd-forward-pad" if buf.ctypes.data in pads else role, buf)
pads = set()
cpu.SCRATCH.take, cpu.SCRATCH.give = take, give
s, cam = case(800, 600, 200_000, 3)
_, cot = run(s, cam, "auto")
for m in ("pad", "asis"):  # each pool warm before timing
    MODE["m"] = m
    run(s, cam, "auto", cot)
res = {m: [] for m in ("asis", "pad")}
for r in range(ROUNDS):
    for m in (["asis", "pad"] if r % 2 == 0 else ["pad", "asis"]):
        MODE["m"] = m
        prof = cProfile.Profile(); prof.enable()
        for _ in range(3): run(s, cam, "auto", cot)
        prof.disable()
        own = B.kernel_seconds(pstats.Stats(prof))
        res[m].append((own["simd.backward_all"] / 3, own["simd.forward_all"] / 3))
for m, v in res.items():
    print(m, "bwd %.4f fwd %.4f" % tuple(statistics.median(x[i] for x in v) for i in range(2)), [round(x[0], 4) for x in v])
