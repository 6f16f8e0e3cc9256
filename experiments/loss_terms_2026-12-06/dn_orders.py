"""L_dn (`losses.normal.depth_normal_loss`) emulated in numpy float32, operation by operation, against
torch's autograd: its value and the gradients of the rendered normal and depth bit for bit, and
each order torch's engine adds gradients in (what a kernel must repeat to keep trained models
bit for bit; the L_smooth prototype beside it is such a kernel). Prints each check.

    python experiments/loss_terms_2026-12-06/dn_orders.py   (from the checkout)

Findings: the forward is torch's elementwise order; inv's gradient adds z, y, x; rsqrt's backward
is (-0.5 g) r^3; each n component's gradient is (from n inv + from sq) + from sq; each P map's
slices add as c[:-2, 1:-1], c[2:, 1:-1], c[1:-1, :-2], c[1:-1, 2:]; depth's gradient adds z, y, x.
"""
import torch
import torch.nn.functional as F


def dn_parts(normal_render, depth, alpha, K):
    H, W = depth.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=depth.dtype), torch.arange(W, dtype=depth.dtype), indexing="ij")
    Kinv = torch.linalg.inv(K.to(depth.dtype))
    P = [((Kinv[i, 0] * xs + Kinv[i, 1] * ys + Kinv[i, 2]) * depth) for i in range(3)]
    for p in P: p.retain_grad()
    def central(c):
        return c[1:-1, 2:] - c[1:-1, :-2], c[2:, 1:-1] - c[:-2, 1:-1]
    (ax, bx), (ay, by), (az, bz) = central(P[0]), central(P[1]), central(P[2])
    nx, ny, nz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax
    for t in (nx, ny, nz): t.retain_grad()
    sq = nx * nx + ny * ny + nz * nz
    sq.retain_grad()
    nonzero = sq > 0
    inv = torch.where(nonzero, torch.rsqrt(torch.where(nonzero, sq, torch.ones_like(sq))), torch.zeros_like(sq))
    inv.retain_grad()
    n_d = F.pad(torch.stack([nx * inv, ny * inv, nz * inv]), (1, 1, 1, 1))
    dot = normal_render[0] * n_d[0] + normal_render[1] * n_d[1] + normal_render[2] * n_d[2]
    loss = (1.0 - dot * alpha.detach()).mean()
    return loss, dict(P=P, nx=nx, ny=ny, nz=nz, sq=sq, inv=inv, n_d=n_d, Kinv=Kinv)
import itertools

import numpy as np
f = np.float32
g = torch.Generator().manual_seed(0)
H, W = 50, 70
depth0 = (2.0 + 0.3 * torch.rand(H, W, generator=g)).float()
depth0[3:6, 3:9] = 0.0
nr_base = torch.randn(H, W, 3, generator=g)
alpha = torch.rand(H, W, generator=g)
K = torch.tensor([[300.0, 0, 35.0], [0, 310.0, 25.0], [0, 0, 1]])
depth = depth0.clone().requires_grad_(True)
nrl = nr_base.clone().requires_grad_(True)
nr = nrl.permute(2, 0, 1)
loss, it = dn_parts(nr, depth, alpha, K)
w = torch.tensor(0.07)
(w * loss).backward()
Kinv = it["Kinv"].numpy()
D = depth0.numpy(); NR = nr_base.numpy(); A = alpha.numpy()
ys, xs = np.meshgrid(np.arange(H, dtype=f), np.arange(W, dtype=f), indexing="ij")
P = [((Kinv[c, 0] * xs + Kinv[c, 1] * ys) + Kinv[c, 2]) * D for c in range(3)]
print("P", all(np.array_equal(P[c], it["P"][c].detach().numpy()) for c in range(3)))
cen = lambda c: (c[1:-1, 2:] - c[1:-1, :-2], c[2:, 1:-1] - c[:-2, 1:-1])
(ax, bx), (ay, by), (az, bz) = cen(P[0]), cen(P[1]), cen(P[2])
nx, ny, nz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax
sq = (nx * nx + ny * ny) + nz * nz
print("sq", np.array_equal(sq, it["sq"].detach().numpy()))
nz_ = sq > 0
inv = np.where(nz_, f(1) / np.sqrt(np.where(nz_, sq, f(1))), f(0))
print("inv", np.array_equal(inv, it["inv"].detach().numpy()))
nd = np.zeros((3, H, W), f); nd[0, 1:-1, 1:-1] = nx * inv; nd[1, 1:-1, 1:-1] = ny * inv; nd[2, 1:-1, 1:-1] = nz * inv
dot = (NR[..., 0] * nd[0] + NR[..., 1] * nd[1]) + NR[..., 2] * nd[2]
mp = f(1) - dot * A
print("loss", torch.equal(torch.from_numpy(mp).mean(), loss.detach()))
# backward
gm = f((w / (H * W)).item()) if False else (w.numpy() / f(H * W)).astype(f)
gdot = (-gm) * A
gnr = np.stack([gdot * nd[c] for c in range(3)], -1)
print("g normal", np.array_equal(gnr, nrl.grad.numpy()), np.abs(gnr - nrl.grad.numpy()).max())
gm_c = [(gdot * NR[..., c])[1:-1, 1:-1] for c in range(3)]
n3 = [nx, ny, nz]
ginv_t = it["inv"].grad.numpy()
for order in ((2, 1, 0), (0, 1, 2)):
    gi = gm_c[order[0]] * n3[order[0]]
    for c in order[1:]:
        gi = gi + gm_c[c] * n3[c]
    print("ginv order", order, np.array_equal(gi, ginv_t))
gi = (gm_c[2] * nz + gm_c[1] * ny) + gm_c[0] * nx
r = np.where(nz_, f(1) / np.sqrt(np.where(nz_, sq, f(1))), f(1))
g_r = np.where(nz_, gi, f(0))
cands = {"(-0.5*g)*((r*r)*r)": (f(-0.5) * g_r) * ((r * r) * r), "(-0.5*g)*(r*(r*r))": (f(-0.5) * g_r) * (r * (r * r)),
         "-0.5*(g*r3)": f(-0.5) * (g_r * ((r * r) * r)), "(g*-0.5)*r3": (g_r * f(-0.5)) * ((r * r) * r),
         "(-0.5*g)*pow": (f(-0.5) * g_r) * np.power(r, f(3)).astype(f)}
gsq_t = it["sq"].grad.numpy()
for k, v in cands.items():
    gsq = np.where(nz_, v, f(0))
    print("gsq", k, np.array_equal(gsq, gsq_t))
gsq = np.where(nz_, (f(-0.5) * g_r) * ((r * r) * r), f(0))
for name, c, nn in (("nx", 0, nx), ("ny", 1, ny), ("nz", 2, nz)):
    tgt = it[name].grad.numpy()
    m = gm_c[c] * inv; s1 = gsq * nn
    cands = {"m+(s+s)": m + (s1 + s1), "(m+s)+s": (m + s1) + s1, "(s+s)+m": (s1 + s1) + m, "(s+m)+s": (s1 + m) + s1}
    print(name, {k: np.array_equal(v, tgt) for k, v in cands.items()})
gn = {}
for name, c, nn in (("nx", 0, nx), ("ny", 1, ny), ("nz", 2, nz)):
    m = gm_c[c] * inv; s1 = gsq * nn
    gn[name] = (m + s1) + s1
gx_, gy_, gz_ = gn["nx"], gn["ny"], gn["nz"]
# nx = by*az - bz*ay ; ny = bz*ax - bx*az ; nz = bx*ay - by*ax
g_ = {
 "by": [gx_ * az, (-gz_) * ax], "az": [gx_ * by, (-gy_) * bx], "bz": [(-gx_) * ay, gy_ * ax], "ay": [(-gx_) * bz, gz_ * bx],
 "ax": [gy_ * bz, (-gz_) * by], "bx": [(-gy_) * az, gz_ * ay],
}
G = {k: v[0] + v[1] for k, v in g_.items()}
def pgrad(ga, gb, order):
    H_, W_ = H, W
    parts = {}
    z = np.zeros((H_, W_), f)
    t = z.copy(); t[1:-1, 2:] = ga; parts["s1"] = t
    t = z.copy(); t[1:-1, :-2] = -ga; parts["s2"] = t
    t = z.copy(); t[2:, 1:-1] = gb; parts["s3"] = t
    t = z.copy(); t[:-2, 1:-1] = -gb; parts["s4"] = t
    acc = parts[order[0]].copy()
    for k in order[1:]:
        acc = acc + parts[k]
    return acc
for c, (a, b) in enumerate((("ax", "bx"), ("ay", "by"), ("az", "bz"))):
    tgt = it["P"][c].grad.numpy()
    ok = [o for o in itertools.permutations(["s1", "s2", "s3", "s4"]) if np.array_equal(pgrad(G[a], G[b], o), tgt)]
    print("P", c, ok[:4], len(ok))
gP = [pgrad(G[a], G[b], ("s4", "s3", "s2", "s1")) for a, b in (("ax", "bx"), ("ay", "by"), ("az", "bz"))]
lin = [((Kinv[c, 0] * xs + Kinv[c, 1] * ys) + Kinv[c, 2]) for c in range(3)]
tgt = depth.grad.numpy()
for order in itertools.permutations([0, 1, 2]):
    acc = gP[order[0]] * lin[order[0]]
    for c in order[1:]:
        acc = acc + gP[c] * lin[c]
    print("depth", order, np.array_equal(acc, tgt))
