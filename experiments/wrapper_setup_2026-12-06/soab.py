"""soab.py REPS A.cpp B.cpp [...]: in one process, renders 800x600/200k through simd with each
variant's kernels alternated (rotating order); median render, forward_all, backward_all, and
checks every variant's maps and gradients equal the first's bit for bit."""
import sys, time, os, statistics, tempfile
HARNESS = __import__("pathlib").Path(__file__).resolve().parent.parent / "setup_simd_2026-12-06" / "harness.py"
from pathlib import Path
import numpy as np, torch
from pipeline import heap; heap.keep_freed_memory()
argv = sys.argv[1:]
sys.argv = ["x", "none"]
exec(open(HARNESS).read().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import simd
reps = int(argv[0]); srcs = argv[1:]
W, H, N = map(int, os.environ.get("CASE", "800,600,200000").split(","))
kern = []
for src in srcs:
    simd.SOURCE = Path(src)
    lib = simd.load(simd.build(simd._compiler(), simd.FLAGS, Path(tempfile.gettempdir()) / "soab"))
    kern.append({n: simd._CFunction(getattr(lib, n), a) for n, a in simd._FUNCTIONS.items()})
times = {"fwd": 0.0, "bwd": 0.0}
f0, b0 = simd.forward_all, simd.backward_all
def fw(*a):
    t = time.perf_counter(); f0(*a); times["fwd"] += time.perf_counter() - t
def bw(*a):
    t = time.perf_counter(); b0(*a); times["bwd"] += time.perf_counter() - t
simd.forward_all, simd.backward_all = fw, bw
s, cam = case(W, H, N, 3)
simd._state["kernels"] = kern[0]
ref, cot = run(s, cam, "simd")
res = {i: {"all": [], "fwd": [], "bwd": []} for i in range(len(srcs))}
for i in range(len(srcs)):
    simd._state["kernels"] = kern[i]
    got, _ = run(s, cam, "simd", cot)
    bad = [k for k in ref if not torch.equal(ref[k], got[k])]
    print(srcs[i], "identical" if not bad else f"DIFFER {bad}")
for r in range(reps):
    order = list(range(len(srcs)))
    order = order[r % len(order):] + order[: r % len(order)]
    if r % 2: order = order[::-1]
    for i in order:
        simd._state["kernels"] = kern[i]
        times["fwd"] = times["bwd"] = 0.0
        t = time.perf_counter(); run(s, cam, "simd", cot); dt = time.perf_counter() - t
        res[i]["all"].append(dt); res[i]["fwd"].append(times["fwd"]); res[i]["bwd"].append(times["bwd"])
base = {k: statistics.median(v) for k, v in res[0].items()}
for i, src in enumerate(srcs):
    m = {k: statistics.median(v) for k, v in res[i].items()}
    print(f"{Path(src).name:28s} " + "  ".join(f"{k} {m[k]*1e3:6.2f} ms ({m[k]/base[k]:.3f})" for k in m))
