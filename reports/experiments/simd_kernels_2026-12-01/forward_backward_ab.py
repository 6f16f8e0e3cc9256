"""Numba forward+backward kernels against the C prototypes, on bench-raster's scene."""
import ctypes, sys, time, os
import numpy as np, torch, numba
from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels
from pipeline.rasterizer import cpu as cb, _kernels as K

W, H, N = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
flib, blib = sys.argv[4], sys.argv[5]
import os
M32 = os.environ.get("M32") == "1"
reps = int(sys.argv[6]) if len(sys.argv) > 6 else 9
cam, n2w = dtu_camera(W, H)
s = object_surfels(N, n2w, seed=0)
with torch.no_grad():
    g = cb.prepare(s.means, s.quats, s.scales, s.opacities, cam)
C = 3; dtype = np.float32
feat = s.features.numpy()
_, Rwc, _ = cb._camera_arrays(cam)
Rwc = np.ascontiguousarray(Rwc, np.float64)
n_rec, n_pairs = int(g.rec_tile_start[-1]), g.num_pairs
RS = n_rec + 16
ent = np.empty((n_pairs, K.E_FEAT + C))
K.gather_entries(g.tile_list, g.geo, g.Tm, g.nrm, g.box, feat, ent)
RHO = float(os.environ.get("RHO_CAP", "inf"))
print("entries with rho_max > cap:", (ent[:, K.GEO_RHO_MAX] > RHO).mean())
ent[:, K.GEO_RHO_MAX] = np.minimum(ent[:, K.GEO_RHO_MAX], RHO)
rng = np.random.default_rng(1)
cots = [rng.standard_normal((H, W, C)).astype(dtype)] + [rng.standard_normal((H, W)).astype(dtype) for _ in range(3)]
cots += [rng.standard_normal((H, W, 3)).astype(dtype) for _ in range(2)] + [rng.standard_normal((H, W)).astype(dtype)]

def alloc(soa):
    maps = [np.zeros((H, W, C), dtype)] + [np.zeros((H, W), dtype) for _ in range(3)]
    maps += [np.zeros((H, W, 3), dtype), np.zeros((H, W, 3), dtype), np.zeros((H, W), dtype)]
    aux = [np.zeros((H, W)) for _ in range(5)]
    med_local = np.zeros((H, W), np.int32)
    rec = np.zeros(3 * RS, dtype) if soa else np.zeros((n_rec, K.R_SIZE), dtype)
    return dict(maps=maps, aux=aux, med=med_local, rec=rec, rs=np.zeros(n_pairs, np.int64), rc=np.zeros(n_pairs, np.int64),
                slots=np.zeros((n_pairs, K.S_FIXED + C)), rmask=np.zeros(n_pairs * 48, np.uint16))

def nb_fwd(b):
    K.forward(g.tile_start, g.worker_start, g.worker_tiles, ent, Rwc, W, g.n_tx, cam.near, cam.far, 1e-6,
              *b["maps"], *b["aux"], b["med"], g.rec_tile_start, b["rec"], b["rs"], b["rc"])
def nb_bwd(b):
    K.backward(g.tile_start, g.slot_of_entry, g.worker_start, g.worker_tiles, ent, Rwc, W, g.n_tx, cam.near, cam.far, 1e-6,
               *b["aux"], b["med"], b["rec"], b["rs"], b["rc"], *cots, b["slots"])
P = lambda a: a.ctypes.data_as(ctypes.c_void_p)
I, D = ctypes.c_int64, ctypes.c_double
FL, BL = ctypes.CDLL(flib), ctypes.CDLL(blib)
nw = len(g.worker_start) - 1
def c_fwd(b):
    FL.forward(P(g.tile_start), P(g.worker_start), P(g.worker_tiles), I(nw), P(ent), I(ent.shape[1]), I(C), P(Rwc),
               I(W), I(H), I(g.n_tx), D(cam.near), D(cam.far), D(1e-6), *[P(m) for m in b["maps"]], *[P(a) for a in b["aux"]],
               P(b["med"]), P(g.rec_tile_start), P(b["rec"]), P(b["rs"]), P(b["rc"]), *([P(b["rmask"])] if M32 else []))
def c_bwd(b):
    BL.backward(P(g.tile_start), P(g.slot_of_entry), P(g.worker_start), P(g.worker_tiles), I(nw), P(ent), I(ent.shape[1]), I(C),
                P(Rwc), I(W), I(H), I(g.n_tx), D(cam.near), D(cam.far), D(1e-6), *[P(a) for a in b["aux"]], P(b["med"]),
                P(b["rec"]), P(b["rs"]), P(b["rc"]), *[P(c) for c in cots], P(b["slots"]), I(RS), *([P(b["rmask"])] if M32 else []))
bn, bc = alloc(False), alloc(True)
nb_fwd(bn); nb_bwd(bn); c_fwd(bc); c_bwd(bc)
sn, sc = bn["slots"], bc["slots"]
scale = np.abs(sn).max(axis=0)
rel = np.abs(sn - sc).max(axis=0) / np.maximum(scale, 1e-300)
print("slots rel diff per column:", np.array2string(rel, precision=2))
print("slots: max abs diff / column max:", np.round(np.abs(sn - sc).max(axis=0) / np.maximum(scale, 1e-300), 12).max(),
      "rec_count equal", np.array_equal(bn["rc"], bc["rc"]), "composited", bn["rc"].sum())
ts = {k: [] for k in ("nb_fwd", "nb_bwd", "c_fwd", "c_bwd")}
for _ in range(reps):
    for k, f, b in (("nb_fwd", nb_fwd, bn), ("nb_bwd", nb_bwd, bn), ("c_fwd", c_fwd, bc), ("c_bwd", c_bwd, bc)):
        t0 = time.perf_counter(); f(b); ts[k].append(time.perf_counter() - t0)
for k, v in ts.items():
    print(k, "median %.4f min %.4f" % (np.median(v), np.min(v)))
print("numba fwd+bwd %.4f, C fwd+bwd %.4f, ratio %.2f" % (np.median(ts["nb_fwd"]) + np.median(ts["nb_bwd"]),
      np.median(ts["c_fwd"]) + np.median(ts["c_bwd"]), (np.median(ts["c_fwd"]) + np.median(ts["c_bwd"])) / (np.median(ts["nb_fwd"]) + np.median(ts["nb_bwd"]))))
