"""A prototype: L_dn (``losses.normal.depth_normal_loss``) with its per-pixel work in numba kernels
in torch's order of operations and of gradient accumulation (found by ``dn_orders.py``), the mean
over the map left to torch; checked bit for bit against the torch term, and timed.

    python experiments/loss_terms_2026-12-06/dn_kernel.py [H W]   (from the checkout)

The kernels compile on each run (``cache=False``: a module loaded by path cannot use numba's cache).
"""
from __future__ import annotations

import sys
import time

import numpy as np
import torch
from numba import njit, prange

from pipeline.losses.normal import depth_normal_loss


@njit(inline="always")
def _lin(Ki, c, i, j):
    return (Ki[c, 0] * np.float32(j) + Ki[c, 1] * np.float32(i)) + Ki[c, 2]


@njit(parallel=True, cache=False, error_model="numpy")
def _forward(d, nr, alpha, Ki, P, nd, inv, n3, out):
    """``P`` (3, H, W) back-projected points, ``n3`` (3, H-2, W-2) the cross products, ``inv``
    their inverse lengths, ``nd`` (3, H, W) the depth normals (0 on the border), ``out`` the
    map ``1 - n_render . n_d alpha``."""
    H, W = d.shape
    zero = np.float32(0.0)
    for i in prange(H):
        for j in range(W):
            for c in range(3):
                P[c, i, j] = _lin(Ki, c, i, j) * d[i, j]
    for i in prange(H):
        for j in range(W):
            if 0 < i < H - 1 and 0 < j < W - 1:
                u, v = i - 1, j - 1
                ax, bx = P[0, i, j + 1] - P[0, i, j - 1], P[0, i + 1, j] - P[0, i - 1, j]
                ay, by = P[1, i, j + 1] - P[1, i, j - 1], P[1, i + 1, j] - P[1, i - 1, j]
                az, bz = P[2, i, j + 1] - P[2, i, j - 1], P[2, i + 1, j] - P[2, i - 1, j]
                nx, ny, nz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax
                n3[0, u, v], n3[1, u, v], n3[2, u, v] = nx, ny, nz
                sq = (nx * nx + ny * ny) + nz * nz
                iv = np.float32(1.0) / np.sqrt(sq) if sq > 0 else zero
                inv[u, v] = iv
                nd[0, i, j], nd[1, i, j], nd[2, i, j] = nx * iv, ny * iv, nz * iv
            else:
                nd[0, i, j] = nd[1, i, j] = nd[2, i, j] = zero
            dot = (nr[i, j, 0] * nd[0, i, j] + nr[i, j, 1] * nd[1, i, j]) + nr[i, j, 2] * nd[2, i, j]
            out[i, j] = np.float32(1.0) - dot * alpha[i, j]


@njit(parallel=True, cache=False, error_model="numpy")
def _backward(d, nr, alpha, Ki, P, nd, inv, n3, gm, g_nr, GA, GB, g_d):
    """``g_nr`` (H, W, 3) and ``g_d`` (H, W): the gradients of the rendered normal and depth for
    the mean's gradient ``gm``, accumulated in torch's engine's order (``dn_orders.py``).
    ``GA``, ``GB`` (3, H-2, W-2): scratch, the central differences' gradients."""
    H, W = d.shape
    zero = np.float32(0.0)
    half = np.float32(-0.5)
    for i in prange(H):
        for j in range(W):
            gdot = (-gm) * alpha[i, j]
            for c in range(3):
                g_nr[i, j, c] = gdot * nd[c, i, j]
            if not (0 < i < H - 1 and 0 < j < W - 1):
                continue
            u, v = i - 1, j - 1
            nx, ny, nz = n3[0, u, v], n3[1, u, v], n3[2, u, v]
            iv = inv[u, v]
            gmx, gmy, gmz = gdot * nr[i, j, 0], gdot * nr[i, j, 1], gdot * nr[i, j, 2]
            gi = (gmz * nz + gmy * ny) + gmx * nx
            nonzero = ((nx * nx + ny * ny) + nz * nz) > 0
            r = iv if nonzero else np.float32(1.0)
            gsq = (half * gi) * ((r * r) * r) if nonzero else zero
            gx = (gmx * iv + gsq * nx) + gsq * nx
            gy = (gmy * iv + gsq * ny) + gsq * ny
            gz = (gmz * iv + gsq * nz) + gsq * nz
            ax, bx = P[0, i, j + 1] - P[0, i, j - 1], P[0, i + 1, j] - P[0, i - 1, j]
            ay, by = P[1, i, j + 1] - P[1, i, j - 1], P[1, i + 1, j] - P[1, i - 1, j]
            az, bz = P[2, i, j + 1] - P[2, i, j - 1], P[2, i + 1, j] - P[2, i - 1, j]
            # nx = by az - bz ay, ny = bz ax - bx az, nz = bx ay - by ax
            GA[0, u, v] = gy * bz + (-gz) * by
            GB[0, u, v] = (-gy) * az + gz * ay
            GA[1, u, v] = (-gx) * bz + gz * bx
            GB[1, u, v] = gx * az + (-gz) * ax
            GA[2, u, v] = gx * by + (-gy) * bx
            GB[2, u, v] = (-gx) * ay + gy * ax
    for i in prange(H):
        for j in range(W):
            acc = zero
            for c in (2, 1, 0):
                # the slices c[:-2, 1:-1], c[2:, 1:-1], c[1:-1, :-2], c[1:-1, 2:] in that order
                inner_j = 1 <= j <= W - 2
                t = -GB[c, i, j - 1] if (i <= H - 3 and inner_j) else zero
                t = t + (GB[c, i - 2, j - 1] if (i >= 2 and inner_j) else zero)
                t = t + (-GA[c, i - 1, j] if (1 <= i <= H - 2 and j <= W - 3) else zero)
                t = t + (GA[c, i - 1, j - 2] if (1 <= i <= H - 2 and j >= 2) else zero)
                term = t * _lin(Ki, c, i, j)
                acc = term if c == 2 else acc + term
            g_d[i, j] = acc


class _DepthNormal(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal_render, depth, alpha, Kinv):
        H, W = depth.shape
        d = depth.detach().contiguous().numpy()
        nr = normal_render.detach().permute(1, 2, 0).numpy()  # (H, W, 3): the renders' own layout
        a = alpha.detach().contiguous().numpy()
        Ki = Kinv.contiguous().numpy()
        P, nd = np.empty((3, H, W), np.float32), np.empty((3, H, W), np.float32)
        inv, n3 = np.zeros((H - 2, W - 2), np.float32), np.zeros((3, H - 2, W - 2), np.float32)
        out = np.empty((H, W), np.float32)
        _forward(d, nr, a, Ki, P, nd, inv, n3, out)
        ctx.save = (d, nr, a, Ki, P, nd, inv, n3)
        return torch.from_numpy(out).mean()

    @staticmethod
    def backward(ctx, g):
        d, nr, a, Ki, P, nd, inv, n3 = ctx.save
        H, W = d.shape
        gm = np.float32((g / (H * W)).item())  # the mean's backward: grad / numel
        g_nr, g_d = np.empty((H, W, 3), np.float32), np.empty((H, W), np.float32)
        GA, GB = np.zeros((3, H - 2, W - 2), np.float32), np.zeros((3, H - 2, W - 2), np.float32)
        _backward(d, nr, a, Ki, P, nd, inv, n3, gm, g_nr, GA, GB, g_d)
        return torch.from_numpy(g_nr).permute(2, 0, 1), torch.from_numpy(g_d), None, None


def dn_fused(normal_render, depth, alpha, K):
    return _DepthNormal.apply(normal_render, depth, alpha, torch.linalg.inv(K.to(depth.dtype)))


def _case(fn, nr_base, depth0, alpha, K, weight):
    nrl, d = nr_base.clone().requires_grad_(True), depth0.clone().requires_grad_(True)
    loss = fn(nrl.permute(2, 0, 1), d, alpha, K)
    (weight * loss).backward()
    return loss.detach(), nrl.grad, d.grad


def main():
    H, W = (int(sys.argv[1]), int(sys.argv[2])) if len(sys.argv) > 2 else (300, 400)
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[0.75 * W, 0.0, W / 2 - 0.5], [0.0, 0.78 * W, H / 2 - 0.5], [0.0, 0.0, 1.0]])
    for trial in range(3):
        depth0 = (2.0 + 0.3 * torch.rand(H, W, generator=g)).float()
        depth0[3:6, 3:9] = 0.0  # no surface
        depth0[10:14, 10:12] = 2.0  # flat: equal depths
        nr_base = torch.randn(H, W, 3, generator=g)
        alpha = torch.rand(H, W, generator=g)
        w = torch.tensor(0.07 + trial)
        (la, gna, gda), (lb, gnb, gdb) = (_case(fn, nr_base, depth0, alpha, K, w) for fn in (depth_normal_loss, dn_fused))
        print(f"trial {trial}: value {'identical' if torch.equal(la, lb) else 'differs'}, normal gradient "
              f"{'identical' if torch.equal(gna, gnb) else f'differs, max {(gna - gnb).abs().max().item():.3g}'}, depth gradient "
              f"{'identical' if torch.equal(gda, gdb) else f'differs, max {(gda - gdb).abs().max().item():.3g}'}")
    for name, fn in (("torch", depth_normal_loss), ("kernels", dn_fused)):
        ts = []
        for _ in range(30):
            t = time.perf_counter()
            _case(fn, nr_base, depth0, alpha, K, w)
            ts.append(time.perf_counter() - t)
        print(f"{name}: forward + backward {np.median(ts[5:]) * 1e3:.2f} ms (median, {H}x{W})")


if __name__ == "__main__":
    main()
