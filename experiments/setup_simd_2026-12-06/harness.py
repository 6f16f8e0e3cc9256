"""``save PATH`` / ``check PATH``: the simd backend's maps and gradients on six scenes, saved,
or compared bit for bit with a saved run (of another tree). ``time REPS W H N``: the
benchmark's scene through ``auto``, each render after a numba one; medians, the ratio, and
cProfile's split into bench-raster's parts. ``KEEP=1``: freed memory kept, as ``gcgs`` does."""
import sys, time, statistics, pickle, cProfile, pstats
import torch, os
if os.environ.get('KEEP'):
    from pipeline import heap; assert heap.keep_freed_memory()
from pipeline.rasterizer import Surfels, rasterize
from pipeline.benchmarks import rasterizer as B
from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels

CASES = [(800, 600, 200_000, 3), (800, 600, 50_000, 3), (400, 300, 50_000, 1), (400, 300, 50_000, 8), (200, 150, 10_000, 5), (123, 77, 3000, 3)]

def case(W, H, N, C):
    cam, n2w = dtu_camera(W, H)
    s = object_surfels(N, n2w, seed=0)
    if C != s.features.shape[1]:
        g = torch.Generator().manual_seed(3)
        s = Surfels(s.means, s.quats, s.scales, s.opacities, torch.rand(N, C, generator=g))
    return s, cam

def run(s, cam, backend, cot=None):
    s = B._leaves(s)
    out = rasterize(s, cam, backend)
    if cot is None:
        g = torch.Generator().manual_seed(1)
        cot = {k: torch.randn(getattr(out, k).shape, generator=g) for k in B.MAPS}
    torch.autograd.backward([getattr(out, k) for k in B.MAPS], [cot[k] for k in B.MAPS])
    res = {k: getattr(out, k).detach().clone() for k in B.MAPS}
    for n in ("means", "quats", "scales", "opacities", "features"):
        res["g_" + n] = getattr(s, n).grad.clone()
    return res, cot

mode = sys.argv[1]
if mode in ("save", "check"):
    path = sys.argv[2]
    got = {}
    for c in CASES:
        s, cam = case(*c)
        got[c], _ = run(s, cam, "simd")
    if mode == "save":
        pickle.dump(got, open(path, "wb"))
    else:
        ref = pickle.load(open(path, "rb"))
        bad = 0
        for c in CASES:
            for k in ref[c]:
                if not torch.equal(ref[c][k], got[c][k]):
                    bad += 1
                    print("DIFF", c, k, float((ref[c][k] - got[c][k]).abs().max()))
        print("identical" if not bad else f"{bad} differ")
elif mode == "time":
    reps, W, H, N = map(int, sys.argv[2:6])
    s, cam = case(W, H, N, 3)
    _, cot = run(s, cam, "auto")
    run(s, cam, "cpu", cot)
    ta, tc = [], []
    prof = cProfile.Profile()
    for _ in range(reps):
        t0 = time.perf_counter(); run(s, cam, "cpu", cot); tc.append(time.perf_counter() - t0)
        prof.enable()
        t0 = time.perf_counter(); run(s, cam, "auto", cot); ta.append(time.perf_counter() - t0)
        prof.disable()
    own = B.kernel_seconds(pstats.Stats(prof))
    split = {p: round(sum(own[f] for f in fs) / reps, 4) for p, fs in B.KERNEL_PARTS.items()}
    print(f"auto median {statistics.median(ta):.4f} min {min(ta):.4f}  cpu median {statistics.median(tc):.4f}  ratio {statistics.median(ta)/statistics.median(tc):.3f}", split)
