import sys, time, os, statistics
HARNESS = __import__("pathlib").Path(__file__).resolve().parent.parent / "setup_simd_2026-12-06" / "harness.py"
import numpy as np, torch, numba
from pipeline import heap; heap.keep_freed_memory()
sys.argv = ["x", "none"]
exec(open(HARNESS).read().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import simd, cpu
times = {"fwd": 0.0, "bwd": 0.0, "gather": 0.0}
f0, b0 = simd.forward_all, simd.backward_all
MODE = {"g": False}
@numba.njit(parallel=True, cache=True)
def gather(surf, tile_list, out):
    n = tile_list.shape[0]
    for c in numba.prange(-(-n // 4096)):
        for j in range(c * 4096, min(n, (c + 1) * 4096)):
            out[j, :] = surf[tile_list[j], :]
store = {}
def fw(fwd, nw, tile_start, tile_order, tile_list, surf, *rest):
    if MODE["g"]:
        t = time.perf_counter()
        g = np.empty((tile_list.shape[0], surf.shape[1]), np.float32); gather(surf, tile_list, g)
        ar = np.arange(tile_list.shape[0], dtype=np.int32)
        times["gather"] += time.perf_counter() - t
        store["g"], store["ar"] = g, ar
        tile_list, surf = ar, g
    t = time.perf_counter(); f0(fwd, nw, tile_start, tile_order, tile_list, surf, *rest); times["fwd"] += time.perf_counter() - t
def bw(bwd, nw, tile_start, slot_of_entry, tile_order, tile_list, surf, *rest):
    if MODE["g"]:
        tile_list, surf = store["ar"], store["g"]
    t = time.perf_counter(); b0(bwd, nw, tile_start, slot_of_entry, tile_order, tile_list, surf, *rest); times["bwd"] += time.perf_counter() - t
simd.forward_all, simd.backward_all = fw, bw
s, cam = case(800, 600, 200000, 3)
ref, cot = run(s, cam, "simd")
MODE["g"] = True
got, _ = run(s, cam, "simd", cot)
print("identical" if all(torch.equal(ref[k], got[k]) for k in ref) else "DIFFER")
res = {m: {k: [] for k in ("all", "fwd", "bwd", "gather")} for m in (False, True)}
for r in range(int(os.environ.get("REPS", "10"))):
    for m in ((False, True) if r % 2 == 0 else (True, False)):
        MODE["g"] = m
        for k in times: times[k] = 0.0
        t = time.perf_counter(); run(s, cam, "simd", cot); dt = time.perf_counter() - t
        res[m]["all"].append(dt)
        for k in times: res[m][k].append(times[k])
for m in res:
    print("gathered" if m else "by id   ", "  ".join(f"{k} {statistics.median(v)*1e3:6.2f}" for k, v in res[m].items()))
