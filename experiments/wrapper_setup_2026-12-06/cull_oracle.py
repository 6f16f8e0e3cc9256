"""cull_oracle.py [ROUNDS] [--geometric | --bound]: the upper bound of binning fewer (tile, surfel) entries. The benchmark's scene
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
elif "--bound" in ARGS:
    # a cheap conservative test per entry (the one a binning could run): the low-pass disc
    # 2 |p - c|^2 <= rho_max, or the conic Q = q0^2 + q1^2 - rho_max q2^2 <= 0 (rho3 <= rho_max),
    # reaches the rectangle of the box's pixel centres in the tile; Q's minimum over the
    # rectangle in closed form (interior, else the four edges), a relative margin for rounding
    import numba

    @numba.njit(cache=False)
    def q_at(S, x, y):
        return S[0, 0] * x * x + 2 * S[0, 1] * x * y + S[1, 1] * y * y + 2 * S[0, 2] * x + 2 * S[1, 2] * y + S[2, 2]

    @numba.njit(cache=False)
    def edge_min(S, fixed, lo, hi, along_x):
        # Q on a segment: x = fixed (along y) or y = fixed (along x), minimised in [lo, hi]
        if along_x:
            a, b = S[0, 0], S[0, 1] * fixed + S[0, 2]
        else:
            a, b = S[1, 1], S[0, 1] * fixed + S[1, 2]
        t = min(max(-b / a, lo), hi) if a > 0 else lo
        best = 1e300
        for v in (lo, hi, t):
            q = q_at(S, v, fixed) if along_x else q_at(S, fixed, v)
            best = min(best, q)
        return best

    @numba.njit(cache=False)
    def bound_keep(tile_start, tile_list, geo, box, n_tx, width, height, margin):
        out = np.zeros(tile_list.shape[0], np.bool_)
        S = np.empty((3, 3))
        for t in range(tile_start.shape[0] - 1):
            tx0, ty0 = (t % n_tx) * K.TILE, (t // n_tx) * K.TILE
            for j in range(tile_start[t], tile_start[t + 1]):
                e = geo[tile_list[j]]
                b = box[tile_list[j]]
                xa, xb = max(b[0], tx0), min(b[1], tx0 + K.TILE - 1, width - 1)
                ya, yb = max(b[2], ty0), min(b[3], ty0 + K.TILE - 1, height - 1)
                rho = e[K.GEO_RHO_MAX]
                cx, cy = e[K.GEO_CX], e[K.GEO_CY]
                dx = max(xa - cx, 0.0, cx - xb)
                dy = max(ya - cy, 0.0, cy - yb)
                if 2.0 * (dx * dx + dy * dy) <= rho * (1 + margin) + margin:
                    out[j] = True
                    continue
                # q = M (x, y, 1): rows AX, AY, A0 are the columns of M
                for r in range(3):
                    for c in range(3):
                        S[r, c] = 0.0
                for k in range(3):
                    w = 1.0 if k < 2 else -rho
                    m = (e[K.GEO_AX + k], e[K.GEO_AY + k], e[K.GEO_A0 + k])
                    for r in range(3):
                        for c in range(3):
                            S[r, c] += w * m[r] * m[c]
                det2 = S[0, 0] * S[1, 1] - S[0, 1] * S[0, 1]
                if not (S[0, 0] > 0 and det2 > 0):
                    out[j] = True  # not an ellipse: keep
                    continue
                ex = (S[0, 1] * S[1, 2] - S[1, 1] * S[0, 2]) / det2
                ey = (S[0, 1] * S[0, 2] - S[0, 0] * S[1, 2]) / det2
                if xa <= ex <= xb and ya <= ey <= yb:
                    out[j] = True
                    continue
                qmin = min(edge_min(S, float(ya), float(xa), float(xb), True), edge_min(S, float(yb), float(xa), float(xb), True),
                           edge_min(S, float(xa), float(ya), float(yb), False), edge_min(S, float(xb), float(ya), float(yb), False))
                # the margin relative to rho_max q2^2 at the ellipse's centre
                q2c = e[K.GEO_AX + 2] * ex + e[K.GEO_AY + 2] * ey + e[K.GEO_A0 + 2]
                out[j] = qmin <= margin * rho * q2c * q2c
        return out

    g64 = cpu.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    assert np.array_equal(g64.tile_list, geom.tile_list)
    keep = bound_keep(g64.tile_start, g64.tile_list, g64.geo, g64.box, g64.n_tx, cam.width, cam.height, 1e-3)
    bound_keep(g64.tile_start, g64.tile_list, g64.geo, g64.box, g64.n_tx, cam.width, cam.height, 1e-3)
    t0 = time.perf_counter()
    bound_keep(g64.tile_start, g64.tile_list, g64.geo, g64.box, g64.n_tx, cam.width, cam.height, 1e-3)
    print(f"the test on every entry, one thread of numba: {(time.perf_counter() - t0) * 1e3:.1f} ms")
else:
    keep = state[6][:n] > 0  # rec_count: entries that composited at least one pair
tile_of = np.repeat(np.arange(geom.tile_start.shape[0] - 1), np.diff(geom.tile_start))
tile_start = np.concatenate([[0], np.cumsum(np.bincount(tile_of[keep], minlength=geom.tile_start.shape[0] - 1))])
culled = cpu.Geometry(geom.Tm, geom.nrm, None, geom.depth, geom.box, geom.radii, geom.centre, tile_start,
                      np.ascontiguousarray(geom.tile_list[keep]), geom.emit_start,
                      np.ascontiguousarray(geom.slot_of_entry[keep]), geom.rec_tile_start, geom.worker_start,
                      geom.worker_tiles, geom.n_tx, geom.surf)
print(f"entries {n}, removed {n - keep.sum()} ({(n - keep.sum()) / n:.1%}): " + ("no candidate pixel" if "--geometric" in ARGS else "the conic and disc miss the tile" if "--bound" in ARGS else "composite nothing"))


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
