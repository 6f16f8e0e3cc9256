"""Time numba's forward kernel on bench-raster's 800x600/200k scene, against a C kernel."""
import ctypes, sys, time
import numpy as np, torch, numba
from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels
from pipeline.rasterizer import cpu as cb, _kernels as K

W, H, N = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
lib = sys.argv[4] if len(sys.argv) > 4 else None
import os
SOA = os.environ.get("SOA") == "1"
reps = 9
cam, n2w = dtu_camera(W, H)
s = object_surfels(N, n2w, seed=0)
with torch.no_grad():
    g = cb.prepare(s.means, s.quats, s.scales, s.opacities, cam)
C = 3
dtype = np.float32
feat = s.features.numpy()
_, Rwc, _ = cb._camera_arrays(cam)
n_rec, n_pairs = int(g.rec_tile_start[-1]), g.num_pairs
ent = np.empty((n_pairs, K.E_FEAT + C))
K.gather_entries(g.tile_list, g.geo, g.Tm, g.nrm, g.box, feat, ent)

def alloc(soa=False):
    maps = [np.zeros((H, W, C), dtype)] + [np.zeros((H, W), dtype) for _ in range(3)]
    maps += [np.zeros((H, W, 3), dtype), np.zeros((H, W, 3), dtype), np.zeros((H, W), dtype)]
    aux = [np.zeros((H, W)) for _ in range(5)]
    med_local = np.zeros((H, W), np.int32)
    rec = np.zeros((n_rec, K.R_SIZE), dtype) if not soa else np.zeros(3 * (n_rec + 16), dtype)
    rs = np.zeros(n_pairs, np.int64); rc = np.zeros(n_pairs, np.int64)
    return maps, aux, med_local, rec, rs, rc

def run_numba(b):
    maps, aux, med_local, rec, rs, rc = b
    K.forward(g.tile_start, g.worker_start, g.worker_tiles, ent, Rwc, W, g.n_tx, cam.near, cam.far, 1e-6,
              *maps, *aux, med_local, g.rec_tile_start, rec, rs, rc)

P = lambda a: a.ctypes.data_as(ctypes.c_void_p)
if lib:
    L = ctypes.CDLL(lib)
    L.forward.restype = None
    def run_c(b):
        maps, aux, med_local, rec, rs, rc = b
        L.forward(P(g.tile_start), P(g.worker_start), P(g.worker_tiles), ctypes.c_int64(len(g.worker_start) - 1),
                  P(ent), ctypes.c_int64(ent.shape[1]), ctypes.c_int64(C), P(np.ascontiguousarray(Rwc, np.float64)),
                  ctypes.c_int64(W), ctypes.c_int64(H), ctypes.c_int64(g.n_tx), ctypes.c_double(cam.near), ctypes.c_double(cam.far),
                  ctypes.c_double(1e-6), *[P(m) for m in maps], *[P(a) for a in aux], P(med_local), P(g.rec_tile_start), P(rec), P(rs), P(rc))

bn, bc = alloc(), alloc(SOA)
run_numba(bn)
if lib:
    run_c(bc)
    names = ["feat", "alpha", "depth", "med", "ncam", "nworld", "dist"]
    for nm, a, b in zip(names, bn[0], bc[0]):
        d = np.abs(a.astype(np.float64) - b)
        print(f"{nm}: max abs diff {d.max():.3g} (max |v| {np.abs(a).max():.3g}), differ>1e-5*max: {(d > 1e-5*np.abs(a).max()).mean():.2e}")
    print("rec_count equal:", np.array_equal(bn[5], bc[5]), "total", bn[5].sum(), bc[5].sum())
    print("med_local equal frac:", (bn[2] == bc[2]).mean())
    soa = bc[3].reshape(3, -1)[:, :n_rec].T if SOA else bc[3]
    print("rec equal frac:", (bn[3] == soa).all(axis=1).mean() if np.array_equal(bn[5], bc[5]) else "-")
ts = {"numba": [], "c": []}
for _ in range(reps):
    for k, f in (("numba", run_numba), ("c", run_c if lib else None)):
        if f is None: continue
        b = bn if k == "numba" else bc
        t0 = time.perf_counter(); f(b); ts[k].append(time.perf_counter() - t0)
for k, v in ts.items():
    if v: print(k, "median %.4f min %.4f" % (np.median(v), np.min(v)))
print("threads", numba.get_num_threads(), "workers", len(g.worker_start) - 1, "entries", n_pairs, "box px", n_rec)
