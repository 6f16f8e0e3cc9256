"""Fused CPU kernels of L_mv's largest part: warp each reference patch into a source through
its plane's homography, sample the source bilinearly and take the NCC, forward and backward
in one pass per patch (numba, parallel over patches).

The torch composition in :mod:`pipeline.losses.multiview` (``_warp_into``, ``_ncc``) is the
reference these kernels are tested against; it keeps ``(M, P)`` intermediates of every step
for autograd, which made the term about a quarter of a CPU training iteration. Here a patch's
``P`` samples live in one scratch row and the backward recomputes them.

Conventions as the reference: ``H`` maps full-resolution reference pixels ``(x, y, 1)`` to
homogeneous source pixels; a sample at ``(x, y)`` in ``[0, W-1] x [0, H-1]`` is bilinear
between integer pixel centres (the last cell serves the last row and column, so a sample on
the image's far edge has the slope of that cell). A patch is *inside* when every warped
point has homogeneous ``w > min_w`` and lies in that range; a patch that is not inside, or
not ``usable``, has NCC 0 and no gradient.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange


@njit(inline="always")
def _warp_sample(Hm, m, x, y, grey, min_w):
    """Warped position, sample and its slopes of one patch point: ``(ok, px, py, w, b, db/dpx, db/dpy)``."""
    Hh, Ww = grey.shape
    u = Hm[m, 0, 0] * x + Hm[m, 0, 1] * y + Hm[m, 0, 2]
    v = Hm[m, 1, 0] * x + Hm[m, 1, 1] * y + Hm[m, 1, 2]
    w = Hm[m, 2, 0] * x + Hm[m, 2, 1] * y + Hm[m, 2, 2]
    if not w > min_w:
        return False, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0
    inv_w = 1.0 / w
    px, py = u * inv_w, v * inv_w
    if not (px >= 0.0 and px <= Ww - 1 and py >= 0.0 and py <= Hh - 1):
        return False, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0
    x0 = min(int(math.floor(px)), max(Ww - 2, 0))
    y0 = min(int(math.floor(py)), max(Hh - 2, 0))
    x1, y1 = min(x0 + 1, Ww - 1), min(y0 + 1, Hh - 1)
    fx, fy = px - x0, py - y0
    i00, i10, i01, i11 = grey[y0, x0], grey[y0, x1], grey[y1, x0], grey[y1, x1]
    top = i00 + fx * (i10 - i00)
    bottom = i01 + fx * (i11 - i01)
    b = top + fy * (bottom - top)
    dbx = (1.0 - fy) * (i10 - i00) + fy * (i11 - i01)
    dby = bottom - top
    return True, px, py, w, b, dbx, dby


@njit(parallel=True, cache=True, error_model="numpy")
def warp_ncc_forward(Hm, ref_pos, grey, a_c, var_a, weight, usable, eps, min_w, ncc, inside, scratch):
    """NCC of each usable patch with its warp (writes ``ncc (M,)``, ``inside (M,)``).

    ``Hm (M, 3, 3)``, ``ref_pos (M, P, 2)`` full-resolution reference positions (x, y),
    ``grey (H, W)`` the source, ``a_c (M, P)`` the reference patches centred by ``weight``
    ``(M, P)`` (support weights summing to 1 per patch), ``var_a (M,)`` their variance,
    ``usable (M,)``; ``scratch (M, P)`` work space."""
    M, P = a_c.shape
    for m in prange(M):
        ncc[m] = 0.0
        inside[m] = False
        if not usable[m]:
            continue
        ok = True
        mean_b = 0.0
        for p in range(P):
            good, px, py, w, b, dbx, dby = _warp_sample(Hm, m, ref_pos[m, p, 0], ref_pos[m, p, 1], grey, min_w)
            if not good:
                ok = False
                break
            scratch[m, p] = b
            mean_b += weight[m, p] * b
        if not ok:
            continue
        cov = 0.0
        var_b = 0.0
        for p in range(P):
            bc = scratch[m, p] - mean_b
            cov += weight[m, p] * a_c[m, p] * bc
            var_b += weight[m, p] * bc * bc
        ncc[m] = cov / math.sqrt(var_a[m] * var_b + eps)
        inside[m] = True


@njit(parallel=True, cache=True, error_model="numpy")
def warp_ncc_backward(Hm, ref_pos, grey, a_c, var_a, weight, inside, eps, min_w, grad_ncc, grad_H, scratch):
    """``grad_H (M, 3, 3)`` of ``sum(grad_ncc * ncc)`` for the patches ``inside`` (0 elsewhere);
    ``scratch (M, P, 6)`` work space.

    d ncc / d b_p = weight_p (a_c_p / D - cov var_a b_c_p / D^3), D = sqrt(var_a var_b + eps)
    (the weighted means of a_c and b_c are 0); b_p moves with the warped position through the
    bilinear slopes, and the position ``(u / w, v / w)`` with ``H``'s rows times ``(x, y, 1)``."""
    M, P = a_c.shape
    for m in prange(M):
        for i in range(3):
            for j in range(3):
                grad_H[m, i, j] = 0.0
        g = grad_ncc[m]
        if not inside[m] or g == 0.0:
            continue
        mean_b = 0.0
        for p in range(P):
            _, px, py, w, b, dbx, dby = _warp_sample(Hm, m, ref_pos[m, p, 0], ref_pos[m, p, 1], grey, min_w)
            scratch[m, p, 0] = b
            scratch[m, p, 1] = px
            scratch[m, p, 2] = py
            scratch[m, p, 3] = w
            scratch[m, p, 4] = dbx
            scratch[m, p, 5] = dby
            mean_b += weight[m, p] * b
        cov = 0.0
        var_b = 0.0
        for p in range(P):
            bc = scratch[m, p, 0] - mean_b
            cov += weight[m, p] * a_c[m, p] * bc
            var_b += weight[m, p] * bc * bc
        D = math.sqrt(var_a[m] * var_b + eps)
        k = cov * var_a[m] / (D * D * D)
        h00 = h01 = h02 = h10 = h11 = h12 = h20 = h21 = h22 = 0.0
        for p in range(P):
            x, y = ref_pos[m, p, 0], ref_pos[m, p, 1]
            px, py, w = scratch[m, p, 1], scratch[m, p, 2], scratch[m, p, 3]
            gb = g * weight[m, p] * (a_c[m, p] / D - k * (scratch[m, p, 0] - mean_b))
            gpx, gpy = gb * scratch[m, p, 4], gb * scratch[m, p, 5]
            gu, gv = gpx / w, gpy / w
            gw = -(gpx * px + gpy * py) / w
            h00 += gu * x
            h01 += gu * y
            h02 += gu
            h10 += gv * x
            h11 += gv * y
            h12 += gv
            h20 += gw * x
            h21 += gw * y
            h22 += gw
        grad_H[m, 0, 0], grad_H[m, 0, 1], grad_H[m, 0, 2] = h00, h01, h02
        grad_H[m, 1, 0], grad_H[m, 1, 1], grad_H[m, 1, 2] = h10, h11, h12
        grad_H[m, 2, 0], grad_H[m, 2, 1], grad_H[m, 2, 2] = h20, h21, h22


@njit(inline="always")
def _patch(grey, cx, cy, patch, ncc_gamma, pos, a, weight):
    """One reference patch around ``(cx, cy)``: fills ``pos (P, 2)``, the centred grey ``a (P,)``
    and the support ``weight (P,)`` (uniform when ``ncc_gamma`` is 0); returns ``(inside,
    variance)``."""
    Hh, Ww = grey.shape
    r = patch // 2
    P = patch * patch
    ok = True
    for p in range(P):
        x = cx + (p % patch - r)
        y = cy + (p // patch - r)
        pos[p, 0] = x
        pos[p, 1] = y
        if not (x >= 0.0 and x <= Ww - 1 and y >= 0.0 and y <= Hh - 1):
            ok = False
        x = min(max(x, 0.0), Ww - 1.0)
        y = min(max(y, 0.0), Hh - 1.0)
        x0 = min(int(math.floor(x)), max(Ww - 2, 0))
        y0 = min(int(math.floor(y)), max(Hh - 2, 0))
        x1, y1 = min(x0 + 1, Ww - 1), min(y0 + 1, Hh - 1)
        fx, fy = x - x0, y - y0
        top = grey[y0, x0] + fx * (grey[y0, x1] - grey[y0, x0])
        bottom = grey[y1, x0] + fx * (grey[y1, x1] - grey[y1, x0])
        a[p] = top + fy * (bottom - top)
    if ncc_gamma > 0:
        centre = a[P // 2]
        total = 0.0
        for p in range(P):
            wp = math.exp(-abs(a[p] - centre) / ncc_gamma)
            weight[p] = wp
            total += wp
        for p in range(P):
            weight[p] = weight[p] / total
    else:
        for p in range(P):
            weight[p] = 1.0 / P
    mean = 0.0
    for p in range(P):
        mean += weight[p] * a[p]
    var = 0.0
    for p in range(P):
        a[p] = a[p] - mean
        var += weight[p] * a[p] * a[p]
    return ok, var


@njit(parallel=True, cache=True, error_model="numpy")
def patch_moments(grey, pix, sx, sy, patch, ncc_gamma, ref_pos, inside, a_c, var_a, weight):
    """The reference patches of training pixels ``pix (M, 2)`` (x, y) in the full-resolution
    ``grey (H, W)`` (writes ``ref_pos (M, P, 2)``, ``inside (M,)``, ``a_c (M, P)``, ``var_a
    (M,)`` and ``weight (M, P)``), as ``multiview._patch_moments``: points at integer offsets,
    row-major over dy, around ``s (x + 0.5) - 0.5``; bilinear samples with positions clamped
    to the image (``grid_sample``'s border padding); support weights ``exp(-|a - a_centre| /
    ncc_gamma)`` normalised to 1, or uniform when ``ncc_gamma`` is 0."""
    for m in prange(pix.shape[0]):
        cx = sx * (pix[m, 0] + 0.5) - 0.5
        cy = sy * (pix[m, 1] + 0.5) - 0.5
        inside[m], var_a[m] = _patch(grey, cx, cy, patch, ncc_gamma, ref_pos[m], a_c[m], weight[m])


@njit(parallel=True, cache=True, error_model="numpy")
def textured_grid(grey, h, w, patch, ncc_gamma, min_std, out):
    """``out (h, w)``: whether each training pixel's patch (as :func:`patch_moments`) is inside
    ``grey`` with a std of at least ``min_std``; the patches live in per-row scratch."""
    Hh, Ww = grey.shape
    sx, sy = Ww / w, Hh / h
    P = patch * patch
    for y in prange(h):
        pos, a, weight = np.empty((P, 2)), np.empty(P, grey.dtype), np.empty(P, grey.dtype)
        cy = sy * (y + 0.5) - 0.5
        for x in range(w):
            ok, var = _patch(grey, sx * (x + 0.5) - 0.5, cy, patch, ncc_gamma, pos, a, weight)
            out[y, x] = ok and math.sqrt(var) >= min_std
