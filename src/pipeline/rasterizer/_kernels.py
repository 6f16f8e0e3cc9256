"""numba kernels of the ``cpu`` backend: tile binning, forward, backward, reduction.

Layout: the image is cut into ``TILE x TILE`` tiles. Every visible surfel is listed in
each tile its support box touches; within a tile the list is front to back (surfels
are emitted in centre-depth order, so a counting sort by tile keeps that order). A
tile is processed by one thread, surfel by surfel, touching only the pixels of the
surfel's box inside the tile, with per-pixel state in small local arrays.

The backward recomputes every pair from the surfel parameters with the *same* helper
and arithmetic as the forward (no fastmath), walks each pixel back to front from its
last contributor, and writes the gradient that a (tile, surfel) pair receives from all
pixels of the tile into that pair's own slot. A final pass sums, for each surfel, its
slots in a fixed order. No atomics and no per-thread buffers: the result is bitwise
identical whatever the number of threads or the scheduling.

Arithmetic is float64 inside (inputs may be float32 or float64; outputs and gradients
take the input dtype). Per-pixel state kept for the backward (transmittance and the
moment sums) is float64.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pipeline.rasterizer.project import ALPHA_MAX, ALPHA_MIN, T_MIN, UV_MAX

TILE = 16
# Gradient slot layout per (tile, surfel) pair / per surfel.
G_T = 0  # 9 entries: dL/dT row-major
G_OPACITY = 9
G_NORMAL = 10  # 3 entries
G_FEATURE = 13  # C entries
G_FIXED = 13
# Pre-test before exp: rho beyond 2 ln(255 o) (plus rounding slack) cannot reach 1/255.
_RHO_SLACK = 1e-6


@njit(cache=True)
def bin_tiles(order, box, n_tx, n_ty):
    """Sort (tile, surfel) pairs by tile, keeping the depth order inside each tile.

    ``order``: visible surfel ids front to back; ``box``: (P, 4) xmin, xmax, ymin, ymax.
    Returns ``tile_start (n_tiles + 1)``, ``tile_list (n_pairs)`` surfel ids,
    ``emit_start (P + 1)`` and ``slot_of_emit (n_pairs)``: surfel ``s``'s pairs, in its
    own row-major tile order, sit at ``slot_of_emit[emit_start[s]:emit_start[s + 1]]``.
    """
    P = box.shape[0]
    n_tiles = n_tx * n_ty
    per_surfel = np.zeros(P + 1, np.int64)
    counts = np.zeros(n_tiles + 1, np.int64)
    for s in order:
        tx0, tx1 = box[s, 0] // TILE, box[s, 1] // TILE
        ty0, ty1 = box[s, 2] // TILE, box[s, 3] // TILE
        per_surfel[s + 1] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
        for ty in range(ty0, ty1 + 1):
            for tx in range(tx0, tx1 + 1):
                counts[ty * n_tx + tx + 1] += 1
    emit_start = np.cumsum(per_surfel)
    tile_start = np.cumsum(counts)
    fill = tile_start[:-1].copy()
    n_pairs = tile_start[-1]
    tile_list = np.empty(n_pairs, np.int32)
    slot_of_emit = np.empty(n_pairs, np.int64)
    for s in order:
        e = emit_start[s]
        for ty in range(box[s, 2] // TILE, box[s, 3] // TILE + 1):
            for tx in range(box[s, 0] // TILE, box[s, 1] // TILE + 1):
                t = ty * n_tx + tx
                tile_list[fill[t]] = s
                slot_of_emit[e] = fill[t]
                fill[t] += 1
                e += 1
    return tile_start, tile_list, emit_start, slot_of_emit


@njit(inline="always")
def _splat(x, y, l0, l1, l2, Tu0, Tu1, Tu2, Tw0, Tw1, Tw2, cx, cy):
    """One pair: ``(rho, z, use3, u, v, k0, k1, k2, q2)`` (see reference._composite)."""
    k0 = x * Tw0 - Tu0
    k1 = x * Tw1 - Tu1
    k2 = x * Tw2 - Tu2
    q0 = k1 * l2 - k2 * l1
    q1 = k2 * l0 - k0 * l2
    q2 = k0 * l1 - k1 * l0
    dx = x - cx
    dy = y - cy
    rho2 = 2.0 * (dx * dx + dy * dy)
    u = 0.0
    v = 0.0
    rho3 = math.inf
    if abs(q2) * UV_MAX > max(abs(q0), abs(q1)):
        u = q0 / q2
        v = q1 / q2
        rho3 = u * u + v * v
    if rho3 <= rho2:
        return rho3, u * Tw0 + v * Tw1 + Tw2, True, u, v, k0, k1, k2, q2
    return rho2, Tw2, False, u, v, k0, k1, k2, q2


@njit(parallel=True, cache=True)
def forward(
    tile_start, tile_list, tile_order, box, Tm, opac, nrm, feat, width, n_tx, near, far,
    out_feat, out_alpha, out_dsum, out_nrm, out_med, out_dist,
    aux_T, aux_W, aux_M1, aux_M2, n_contrib, med_local,
):  # fmt: skip
    """Composite every tile front to back. ``Tm``: (P, 9) row-major ray transforms.

    Writes the six maps and, for the backward, the final transmittance, the moment
    sums ``W = sum w, M1 = sum w m, M2 = sum w m^2`` (float64), the number of list
    entries up to the last contributor (``n_contrib``) and the list position of the
    median-depth surfel (``med_local``, -1 if none), both local to the tile.
    """
    height = out_alpha.shape[0]
    C = feat.shape[1]
    mscale = far / (far - near)
    for it in prange(tile_order.shape[0]):
        t = tile_order[it]
        ty = t // n_tx
        x0 = (t - ty * n_tx) * TILE
        y0 = ty * TILE
        x1 = min(x0 + TILE, width)
        y1 = min(y0 + TILE, height)
        tw = x1 - x0
        npx = tw * (y1 - y0)
        Tr = np.ones(npx)
        Ws = np.zeros(npx)
        M1 = np.zeros(npx)
        M2 = np.zeros(npx)
        D = np.zeros(npx)
        med = np.zeros(npx)
        F = np.zeros((npx, C))
        N = np.zeros((npx, 3))
        medi = np.full(npx, -1, np.int32)
        last = np.zeros(npx, np.int32)
        done = np.zeros(npx, np.bool_)
        n_done = 0
        start = tile_start[t]
        for j in range(start, tile_start[t + 1]):
            if n_done == npx:
                break
            s = tile_list[j]
            bx0 = max(box[s, 0], x0)
            bx1 = min(box[s, 1], x1 - 1)
            by0 = max(box[s, 2], y0)
            by1 = min(box[s, 3], y1 - 1)
            Tu0, Tu1, Tu2 = float(Tm[s, 0]), float(Tm[s, 1]), float(Tm[s, 2])
            Tv0, Tv1, Tv2 = float(Tm[s, 3]), float(Tm[s, 4]), float(Tm[s, 5])
            Tw0, Tw1, Tw2 = float(Tm[s, 6]), float(Tm[s, 7]), float(Tm[s, 8])
            o = float(opac[s])
            rho_max = 2.0 * math.log(255.0 * o) * (1.0 + _RHO_SLACK) + _RHO_SLACK
            cx = Tu2 / Tw2
            cy = Tv2 / Tw2
            n0, n1, n2 = float(nrm[s, 0]), float(nrm[s, 1]), float(nrm[s, 2])
            for py in range(by0, by1 + 1):
                y = float(py)
                l0 = y * Tw0 - Tv0
                l1 = y * Tw1 - Tv1
                l2 = y * Tw2 - Tv2
                row = (py - y0) * tw - x0
                for px in range(bx0, bx1 + 1):
                    p = row + px
                    if done[p]:
                        continue
                    rho, z, use3, u, v, k0, k1, k2, q2 = _splat(
                        float(px), y, l0, l1, l2, Tu0, Tu1, Tu2, Tw0, Tw1, Tw2, cx, cy
                    )
                    if rho > rho_max or z < near:
                        continue
                    a = min(ALPHA_MAX, o * math.exp(-0.5 * rho))
                    if a < ALPHA_MIN:
                        continue
                    T = Tr[p]
                    T_next = T * (1.0 - a)
                    if T_next < T_MIN:
                        done[p] = True
                        n_done += 1
                        continue
                    w = a * T
                    for c in range(C):
                        F[p, c] += w * feat[s, c]
                    N[p, 0] += w * n0
                    N[p, 1] += w * n1
                    N[p, 2] += w * n2
                    D[p] += w * z
                    m = mscale * (1.0 - near / z)
                    Ws[p] += w
                    M1[p] += w * m
                    M2[p] += w * m * m
                    if T > 0.5:
                        med[p] = z
                        medi[p] = j - start
                    last[p] = j - start + 1
                    Tr[p] = T_next
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tw + px - x0
                for c in range(C):
                    out_feat[py, px, c] = F[p, c]
                for c in range(3):
                    out_nrm[py, px, c] = N[p, c]
                out_alpha[py, px] = 1.0 - Tr[p]
                out_dsum[py, px] = D[p]
                out_med[py, px] = med[p]
                # sum_{i>j} w_i w_j (m_i - m_j)^2 == W M2 - M1^2 (exact identity; float64).
                out_dist[py, px] = max(Ws[p] * M2[p] - M1[p] * M1[p], 0.0)
                aux_T[py, px] = Tr[p]
                aux_W[py, px] = Ws[p]
                aux_M1[py, px] = M1[p]
                aux_M2[py, px] = M2[p]
                n_contrib[py, px] = last[p]
                med_local[py, px] = medi[p]


@njit(parallel=True, cache=True)
def backward(
    tile_start, tile_list, tile_order, box, Tm, opac, nrm, feat, width, n_tx, near, far,
    aux_T, aux_W, aux_M1, aux_M2, n_contrib, med_local,
    g_feat, g_alpha, g_dsum, g_nrm, g_med, g_dist, slots,
):  # fmt: skip
    """Gradients per (tile, surfel) pair into ``slots`` (n_pairs, 13 + C).

    Per pixel, walking back to front with ``T_i = T_{i+1} / (1 - a_i)``:
    ``dL/da_i = T_i v_i - S_i / (1 - a_i)``, with ``S_i = sum_{k>i} w_k v_k`` and
    ``v_i = gA + gF.f_i + gD z_i + gN.n_i + gDist dDist/dw_i``, where
    ``dDist/dw_i = m_i^2 W - 2 m_i M1 + M2`` (totals) since ``Dist = W M2 - M1^2``.
    """
    height = aux_T.shape[0]
    C = feat.shape[1]
    G = slots.shape[1]
    mscale = far / (far - near)
    for it in prange(tile_order.shape[0]):
        t = tile_order[it]
        ty = t // n_tx
        x0 = (t - ty * n_tx) * TILE
        y0 = ty * TILE
        x1 = min(x0 + TILE, width)
        y1 = min(y0 + TILE, height)
        tw = x1 - x0
        npx = tw * (y1 - y0)
        Tr = np.empty(npx)
        S = np.zeros(npx)
        max_last = 0
        for py in range(y0, y1):
            for px in range(x0, x1):
                p = (py - y0) * tw + px - x0
                Tr[p] = aux_T[py, px]
                max_last = max(max_last, n_contrib[py, px])
        start = tile_start[t]
        for j in range(start + max_last, tile_start[t + 1]):
            slots[j, :] = 0.0
        acc = np.empty(G)
        for j in range(start + max_last - 1, start - 1, -1):
            li = j - start
            s = tile_list[j]
            acc[:] = 0.0
            bx0 = max(box[s, 0], x0)
            bx1 = min(box[s, 1], x1 - 1)
            by0 = max(box[s, 2], y0)
            by1 = min(box[s, 3], y1 - 1)
            Tu0, Tu1, Tu2 = float(Tm[s, 0]), float(Tm[s, 1]), float(Tm[s, 2])
            Tv0, Tv1, Tv2 = float(Tm[s, 3]), float(Tm[s, 4]), float(Tm[s, 5])
            Tw0, Tw1, Tw2 = float(Tm[s, 6]), float(Tm[s, 7]), float(Tm[s, 8])
            o = float(opac[s])
            rho_max = 2.0 * math.log(255.0 * o) * (1.0 + _RHO_SLACK) + _RHO_SLACK
            cx = Tu2 / Tw2
            cy = Tv2 / Tw2
            n0, n1, n2 = float(nrm[s, 0]), float(nrm[s, 1]), float(nrm[s, 2])
            for py in range(by0, by1 + 1):
                y = float(py)
                l0 = y * Tw0 - Tv0
                l1 = y * Tw1 - Tv1
                l2 = y * Tw2 - Tv2
                row = (py - y0) * tw - x0
                for px in range(bx0, bx1 + 1):
                    if li >= n_contrib[py, px]:
                        continue
                    p = row + px
                    x = float(px)
                    rho, z, use3, u, v, k0, k1, k2, q2 = _splat(
                        x, y, l0, l1, l2, Tu0, Tu1, Tu2, Tw0, Tw1, Tw2, cx, cy
                    )
                    if rho > rho_max or z < near:
                        continue
                    Gv = math.exp(-0.5 * rho)
                    a_raw = o * Gv
                    a = min(ALPHA_MAX, a_raw)
                    if a < ALPHA_MIN:
                        continue
                    T = Tr[p] / (1.0 - a)
                    Tr[p] = T
                    w = a * T
                    m = mscale * (1.0 - near / z)
                    Wt = aux_W[py, px]
                    M1t = aux_M1[py, px]
                    gd = g_dist[py, px]
                    vsum = g_alpha[py, px] + g_dsum[py, px] * z
                    vsum += gd * (m * m * Wt - 2.0 * m * M1t + aux_M2[py, px])
                    gn0, gn1, gn2 = float(g_nrm[py, px, 0]), float(g_nrm[py, px, 1]), float(g_nrm[py, px, 2])
                    vsum += gn0 * n0 + gn1 * n1 + gn2 * n2
                    for c in range(C):
                        gf = float(g_feat[py, px, c])
                        vsum += gf * feat[s, c]
                        acc[G_FEATURE + c] += gf * w
                    acc[G_NORMAL] += gn0 * w
                    acc[G_NORMAL + 1] += gn1 * w
                    acc[G_NORMAL + 2] += gn2 * w
                    dL_da = T * vsum - S[p] / (1.0 - a)
                    S[p] += w * vsum
                    dz = g_dsum[py, px] * w + gd * 2.0 * w * (m * Wt - M1t) * mscale * near / (z * z)
                    if med_local[py, px] == li:
                        dz += g_med[py, px]
                    drho = 0.0
                    if a_raw < ALPHA_MAX:  # the cap has zero derivative
                        acc[G_OPACITY] += dL_da * Gv
                        drho = -0.5 * Gv * o * dL_da
                    if use3:
                        # rho3 = u^2 + v^2, z = u Tw0 + v Tw1 + Tw2, (u, v) = (q0, q1) / q2.
                        du = 2.0 * u * drho + dz * Tw0
                        dv = 2.0 * v * drho + dz * Tw1
                        dq0 = du / q2
                        dq1 = dv / q2
                        dq2 = -(du * u + dv * v) / q2
                        # q = k x l: dL/dk = l x dq, dL/dl = dq x k.
                        dk0 = l1 * dq2 - l2 * dq1
                        dk1 = l2 * dq0 - l0 * dq2
                        dk2 = l0 * dq1 - l1 * dq0
                        dl0 = dq1 * k2 - dq2 * k1
                        dl1 = dq2 * k0 - dq0 * k2
                        dl2 = dq0 * k1 - dq1 * k0
                        # k = x T_w - T_u, l = y T_w - T_v.
                        acc[0] -= dk0
                        acc[1] -= dk1
                        acc[2] -= dk2
                        acc[3] -= dl0
                        acc[4] -= dl1
                        acc[5] -= dl2
                        acc[6] += x * dk0 + y * dl0 + dz * u
                        acc[7] += x * dk1 + y * dl1 + dz * v
                        acc[8] += x * dk2 + y * dl2 + dz
                    else:
                        # rho2 = 2 |(x, y) - c|^2, c = (Tu2, Tv2) / Tw2, z = Tw2.
                        dcx = -4.0 * (x - cx) * drho
                        dcy = -4.0 * (y - cy) * drho
                        acc[2] += dcx / Tw2
                        acc[5] += dcy / Tw2
                        acc[8] += dz - (dcx * cx + dcy * cy) / Tw2
            for g in range(G):
                slots[j, g] = acc[g]


@njit(parallel=True, cache=True)
def reduce_slots(emit_start, slot_of_emit, slots, out):
    """``out[s] = sum of surfel s's slots`` in its fixed emission order (deterministic)."""
    G = slots.shape[1]
    for s in prange(out.shape[0]):
        for e in range(emit_start[s], emit_start[s + 1]):
            j = slot_of_emit[e]
            for g in range(G):
                out[s, g] += slots[j, g]
