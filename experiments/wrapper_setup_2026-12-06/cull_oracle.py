"""cull_oracle.py [ROUNDS] [--geometric]: the upper bound of binning fewer (tile, surfel) entries. The benchmark's scene
(800x600 / 200k) rendered through the simd kernels with its tile lists as binned, and with the
entries that composite no pair removed (an oracle: a conservative per-tile test of the ellipse
could remove at most these; the slots of the removed entries are zero-filled for the
reduction). Maps and gradients compared bit for bit, renders alternated in one process.
They differ: an entry can composite nothing and still end pixels (a pair that would take T
below T_MIN marks the pixel done without compositing), so this oracle overstates what a
results-preserving cull may drop; it bounds the time such a cull can save."""
import sys, time, statistics, weakref
from pathlib import Path
import numpy as np, torch
from pipeline import heap; heap.keep_freed_memory()
ARGS = sys.argv[1:]
sys.argv = ["x", "none"]
exec(open(Path(__file__).resolve().parent.parent / "setup_simd_2026-12-06" / "harness.py").read().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import simd, cpu
from pipeline.rasterizer import _kernels as K
from pipeline.benchmarks import rasterizer as B

s, cam = case(800, 600, 200000, 3)
ref, cot = run(s, cam, "simd")
geom = simd.prepare(s.means, s.quats, s.scales, s.opacities, s.features, cam)


class Ctx:
    pass


_, state = simd.SIMD.forward(Ctx(), geom, cam, 1e-6, s.features.numpy())
n = geom.num_pairs
if "--geometric" in ARGS:
    # entries with a candidate pixel: some box pixel in the tile passes the numba kernel's
    # per-pair test (rho, near, alpha; no transmittance), in float64 on the cpu backend's geo
    import numba

    @numba.njit(cache=False)
    def candidates(tile_start, tile_list, geo, Tm, box, n_tx, width, height, near):
        out = np.zeros(tile_list.shape[0], np.bool_)
        for t in range(tile_start.shape[0] - 1):
            tx0, ty0 = (t % n_tx) * K.TILE, (t // n_tx) * K.TILE
            for j in range(tile_start[t], tile_start[t + 1]):
                e = geo[tile_list[j]]
                b = box[tile_list[j]]
                for py in range(max(b[2], ty0), min(b[3], ty0 + K.TILE - 1, height - 1) + 1):
                    dy = py - e[K.GEO_CY]
                    qr0 = py * e[K.GEO_AY] + e[K.GEO_A0]
                    qr1 = py * e[K.GEO_AY + 1] + e[K.GEO_A0 + 1]
                    qr2 = py * e[K.GEO_AY + 2] + e[K.GEO_A0 + 2]
                    for px in range(max(b[0], tx0), min(b[1], tx0 + K.TILE - 1, width - 1) + 1):
                        ok = K._pair(float(px), dy * dy, qr0, qr1, qr2, e[K.GEO_AX], e[K.GEO_AX + 1], e[K.GEO_AX + 2],
                                     e[K.GEO_CX], e[K.GEO_RHO_MAX], e[K.GEO_DET], e[K.GEO_INV_DET], float(Tm[tile_list[j], 8]),
                                     e[K.GEO_INV_ZC], near, e[K.GEO_OPACITY])[0]
                        if ok:
                            out[j] = True
                            break
                    if out[j]:
                        break
        return out

    g64 = cpu.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    assert np.array_equal(g64.tile_list, geom.tile_list)
    keep = candidates(g64.tile_start, g64.tile_list, g64.geo, g64.Tm, g64.box, g64.n_tx, cam.width, cam.height, cam.near)
else:
    keep = state[6][:n] > 0  # rec_count: entries that composited at least one pair
tile_of = np.repeat(np.arange(geom.tile_start.shape[0] - 1), np.diff(geom.tile_start))
tile_start = np.concatenate([[0], np.cumsum(np.bincount(tile_of[keep], minlength=geom.tile_start.shape[0] - 1))])
culled = cpu.Geometry(geom.Tm, geom.nrm, None, geom.depth, geom.box, geom.radii, geom.centre, tile_start,
                      np.ascontiguousarray(geom.tile_list[keep]), geom.emit_start,
                      np.ascontiguousarray(geom.slot_of_entry[keep]), geom.rec_tile_start, geom.worker_start,
                      geom.worker_tiles, geom.n_tx, geom.surf)
print(f"entries {n}, removed {n - keep.sum()} ({(n - keep.sum()) / n:.1%}): " + ("no candidate pixel" if "--geometric" in ARGS else "composite nothing"))


class Fixed(simd.SimdCompositor):
    """The simd compositor on a fixed geometry (the slots of removed entries zero)."""

    def __init__(self, g):
        self.g = g

    def prepare(self, means, quats, scales, opacities, colors, camera):
        return self.g

    def backward(self, geom, camera, depth_eps, feat, state, grads, slots):
        slots[:] = 0.0
        super().backward(geom, camera, depth_eps, feat, state, grads, slots)


comps = {"as binned": Fixed(geom), "oracle cull": Fixed(culled)}
out = {}
for name, c in comps.items():
    leaves = B._leaves(s)
    maps, *_ = cpu.render(leaves.means, leaves.quats, leaves.scales, leaves.opacities, leaves.features, cam, 1e-6, c)
    torch.autograd.backward(maps, [torch.randn(m.shape, generator=torch.Generator().manual_seed(k)) for k, m in enumerate(maps)])
    out[name] = [m.detach().clone() for m in maps] + [getattr(leaves, f).grad.clone() for f in ("means", "quats", "scales", "opacities", "features")]
print("maps and gradients identical:", all(torch.equal(a, b) for a, b in zip(*out.values())))
res = {k: [] for k in comps}
for r in range(next((int(a) for a in ARGS if a.isdigit()), 16)):
    for name in (list(comps) if r % 2 == 0 else list(comps)[::-1]):
        leaves = B._leaves(s)
        t = time.perf_counter()
        maps, *_ = cpu.render(leaves.means, leaves.quats, leaves.scales, leaves.opacities, leaves.features, cam, 1e-6, comps[name])
        torch.autograd.backward(maps, [torch.ones_like(m) for m in maps])
        res[name].append(time.perf_counter() - t)
base = statistics.median(res["as binned"])
for name, v in res.items():
    print(f"{name:12s} render without the set-up, slots zero-filled {statistics.median(v) * 1e3:6.2f} ms ({statistics.median(v) / base:.3f})")
