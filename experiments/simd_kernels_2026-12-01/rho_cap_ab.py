"""numba kernels with rho_max as committed vs capped at 9 (2DGS's 3 sigma), alternated in one process."""
import sys, time, os
import numpy as np, torch
from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels
from pipeline.rasterizer import cpu as cb, _kernels as K
W, H, N = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]); reps = int(sys.argv[4])
cam, n2w = dtu_camera(W, H)
s = object_surfels(N, n2w, seed=0)
with torch.no_grad():
    g = cb.prepare(s.means, s.quats, s.scales, s.opacities, cam)
C = 3; dtype = np.float32; feat = s.features.numpy()
_, Rwc, _ = cb._camera_arrays(cam); Rwc = np.ascontiguousarray(Rwc, np.float64)
n_rec, n_pairs = int(g.rec_tile_start[-1]), g.num_pairs
ent = np.empty((n_pairs, K.E_FEAT + C)); K.gather_entries(g.tile_list, g.geo, g.Tm, g.nrm, g.box, feat, ent)
ent9 = ent.copy(); ent9[:, K.GEO_RHO_MAX] = np.minimum(ent9[:, K.GEO_RHO_MAX], 9.0)
rng = np.random.default_rng(1)
cots = [rng.standard_normal((H, W, C)).astype(dtype)] + [rng.standard_normal((H, W)).astype(dtype) for _ in range(3)]
cots += [rng.standard_normal((H, W, 3)).astype(dtype) for _ in range(2)] + [rng.standard_normal((H, W)).astype(dtype)]
def alloc():
    maps = [np.zeros((H, W, C), dtype)] + [np.zeros((H, W), dtype) for _ in range(3)]
    maps += [np.zeros((H, W, 3), dtype), np.zeros((H, W, 3), dtype), np.zeros((H, W), dtype)]
    return dict(maps=maps, aux=[np.zeros((H, W)) for _ in range(5)], med=np.zeros((H, W), np.int32),
                rec=np.zeros((n_rec, K.R_SIZE), dtype), rs=np.zeros(n_pairs, np.int64), rc=np.zeros(n_pairs, np.int64),
                slots=np.zeros((n_pairs, K.S_FIXED + C)))
def fb(e, b):
    t0 = time.perf_counter()
    K.forward(g.tile_start, g.worker_start, g.worker_tiles, e, Rwc, W, g.n_tx, cam.near, cam.far, 1e-6,
              *b["maps"], *b["aux"], b["med"], g.rec_tile_start, b["rec"], b["rs"], b["rc"])
    t1 = time.perf_counter()
    K.backward(g.tile_start, g.slot_of_entry, g.worker_start, g.worker_tiles, e, Rwc, W, g.n_tx, cam.near, cam.far, 1e-6,
               *b["aux"], b["med"], b["rec"], b["rs"], b["rc"], *cots, b["slots"])
    return t1 - t0, time.perf_counter() - t1
b0, b9 = alloc(), alloc()
fb(ent, b0); fb(ent9, b9)
print("composited", b0["rc"].sum(), b9["rc"].sum(), "alpha max diff", np.abs(b0["maps"][1] - b9["maps"][1]).max(),
      "colour max diff", np.abs(b0["maps"][0] - b9["maps"][0]).max())
t = {"committed": [], "cap9": []}
for _ in range(reps):
    t["committed"].append(fb(ent, b0)); t["cap9"].append(fb(ent9, b9))
for k, v in t.items():
    v = np.array(v); print(k, "fwd %.4f bwd %.4f total %.4f" % (np.median(v[:, 0]), np.median(v[:, 1]), np.median(v.sum(1))))
print("ratio cap9/committed %.3f" % (np.median(np.array(t["cap9"]).sum(1)) / np.median(np.array(t["committed"]).sum(1))))
