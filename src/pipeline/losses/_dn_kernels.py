"""2DGS depth-normal consistency L_dn's per-pixel work as CPU kernels (numba, parallel over
rows), float32.

:func:`pipeline.losses.normal._depth_normal_loss_torch` (back-projection, central
differences, cross product, normalisation, dot product) is some forty passes over the map
with its autograd; these kernels do the forward in two passes and the backward in two, in
torch's order of operations and of its engine's gradient accumulation, so that value and
gradients are torch's to the last bit (tested). The orders: the inverse length's gradient
adds z, y, x; rsqrt's backward is ``(-0.5 g) r^3``; each cross-product component's gradient
is ``(through n inv + through |n|^2) + through |n|^2``; each point map's four slices add as
``c[:-2, 1:-1], c[2:, 1:-1], c[1:-1, :-2], c[1:-1, 2:]``; the depth's gradient adds z, y, x.

Maps: depth and alpha ``(H, W)`` C-contiguous, rendered normals ``(H, W, 3)`` (any strides),
``Kinv`` the inverse intrinsics (pixel centres at integer coordinates), ``H, W >= 3``.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange


@njit(inline="always")
def _ray(Kinv, c, i, j):
    """Component ``c`` of ``Kinv (j, i, 1)``, summed as torch's expression."""
    return (Kinv[c, 0] * np.float32(j) + Kinv[c, 1] * np.float32(i)) + Kinv[c, 2]


@njit(parallel=True, cache=True, error_model="numpy")
def forward(depth, normal, alpha, Kinv, P, nd, inv, n3, out):
    """``P`` ``(3, H, W)``: the back-projected points; ``n3`` ``(3, H-2, W-2)``: the cross
    products of the central differences; ``inv``: their inverse lengths (0 where they
    vanish); ``nd`` ``(3, H, W)``: the depth's unit normals (0 on the border); ``out``
    ``(H, W)``: ``1 - normal . nd alpha``."""
    H, W = depth.shape
    zero = np.float32(0.0)
    for i in prange(H):
        for j in range(W):
            for c in range(3):
                P[c, i, j] = _ray(Kinv, c, i, j) * depth[i, j]
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
            dot = (normal[i, j, 0] * nd[0, i, j] + normal[i, j, 1] * nd[1, i, j]) + normal[i, j, 2] * nd[2, i, j]
            out[i, j] = np.float32(1.0) - dot * alpha[i, j]


@njit(parallel=True, cache=True, error_model="numpy")
def backward(depth, normal, alpha, Kinv, P, nd, inv, n3, g_mean, g_normal, GA, GB, g_depth):
    """``g_normal`` ``(H, W, 3)`` and ``g_depth`` ``(H, W)``: the gradients of the rendered
    normal and depth for ``g_mean``, the loss's gradient over the pixel count. ``GA``, ``GB``
    ``(3, H-2, W-2)``: scratch, the gradients of the horizontal and vertical differences."""
    H, W = depth.shape
    zero = np.float32(0.0)
    half = np.float32(-0.5)
    for i in prange(H):
        for j in range(W):
            gdot = (-g_mean) * alpha[i, j]
            for c in range(3):
                g_normal[i, j, c] = gdot * nd[c, i, j]
            if not (0 < i < H - 1 and 0 < j < W - 1):
                continue
            u, v = i - 1, j - 1
            nx, ny, nz = n3[0, u, v], n3[1, u, v], n3[2, u, v]
            iv = inv[u, v]
            gmx, gmy, gmz = gdot * normal[i, j, 0], gdot * normal[i, j, 1], gdot * normal[i, j, 2]
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
            inner_j = 1 <= j <= W - 2
            inner_i = 1 <= i <= H - 2
            for c in (2, 1, 0):
                t = -GB[c, i, j - 1] if (i <= H - 3 and inner_j) else zero
                t = t + (GB[c, i - 2, j - 1] if (i >= 2 and inner_j) else zero)
                t = t + (-GA[c, i - 1, j] if (inner_i and j <= W - 3) else zero)
                t = t + (GA[c, i - 1, j - 2] if (inner_i and j >= 2) else zero)
                term = t * _ray(Kinv, c, i, j)
                acc = term if c == 2 else acc + term
            g_depth[i, j] = acc
