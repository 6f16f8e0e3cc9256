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
for i in os.environ.get('ZERO', '').split(','):
    if i: cots[int(i)][:] = 0

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
if os.environ.get("CHECK") == "1":
    bad_tiles = set()
    ts_ = g.tile_start
    mism = np.flatnonzero(bn["rc"] != bc["rc"])
    tile_of = np.searchsorted(ts_, np.arange(n_pairs), side="right") - 1
    bad = np.isin(tile_of, np.unique(tile_of[mism]))
    sl = g.slot_of_entry
    d = np.abs(sn[sl[~bad]] - sc[sl[~bad]]).max(axis=0) / np.maximum(scale, 1e-300)
    print("tiles with a flipped record:", len(np.unique(tile_of[mism])), "slots elsewhere, rel diff per column:", np.array2string(d, precision=2))
if os.environ.get("CHECK") == "1":
    col = int(os.environ.get("COL", "2"))
    good = np.flatnonzero(~bad)
    dd = np.abs(sn[sl[good], col] - sc[sl[good], col])
    for k in np.argsort(dd)[::-1][:5]:
        j = good[k]
        print("entry", j, "recs", bn["rc"][j], "numba", sn[sl[j], col], "C", sc[sl[j], col], "colmax", scale[col],
              "rho_max", ent[j, K.GEO_RHO_MAX], "box", ent[j, K.E_BOX:K.E_BOX+4], "o", ent[j, K.GEO_OPACITY])
        r0, rn = bn["rs"][j], bn["rc"][j]
        print("   use3 frac", ((bn["rec"][r0:r0+rn, 0].astype(int) & 256) > 0).mean(), "T", bn["rec"][r0:r0+rn, 1].min(), "a", bn["rec"][r0:r0+rn, 2].max())
if os.environ.get("CHECK") == "1" and M32:
    flips = 0; checked = 0
    for k in np.argsort(dd)[::-1][:200]:
        j = good[k]
        rm = bc["rmask"][j * 48:(j + 1) * 48].reshape(16, 3)
        cu = []
        for ry in range(16):
            for l in range(16):
                if rm[ry, 0] >> l & 1:
                    cu.append(rm[ry, 1] >> l & 1)
        r0, rn = bn["rs"][j], bn["rc"][j]
        nu = ((bn["rec"][r0:r0 + rn, 0].astype(int) & 256) > 0).astype(int)
        checked += 1
        flips += int(len(cu) != len(nu) or np.any(np.array(cu) != nu))
    print(f"of the {checked} worst entries, {flips} have a use3 flip")
if os.environ.get("CHECK") == "1":
    rel = np.abs(sn[sl[good]] - sc[sl[good]]) / np.maximum(scale, 1e-300)
    for q in (50, 99, 99.9, 99.99, 100):
        print(f"pct {q}: max over columns {np.percentile(rel, q, axis=0).max():.2e}")
