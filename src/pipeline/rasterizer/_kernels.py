"""numba kernels of the ``cpu`` backend.

Pipeline: ``preprocess`` (per surfel: ray transform, facing normal, support box, the tiles
of its box it reaches) -> tile binning -> ``gather_entries`` (each list entry's surfel data, in list order) ->
``forward`` -> ``backward`` -> ``reduce_and_chain`` (per surfel: sum of its pair
gradients, then the chain rule back to means, quats, scales).

Per-pair algebra. With ``T`` the ray transform (rows ``T_u, T_v, T_w``), the
intersection ``q = k x l`` of pixel ``(x, y)`` is affine in the pixel:
``q = x (T_v x T_w) + y (T_w x T_u) + T_u x T_v = adj(T) (x, y, 1)``, and since
``T_w . q = det T`` the intersection depth is ``z = u T_w0 + v T_w1 + T_w2 = det T / q_2``.
``rho3 <= rho_max`` reads ``q_0^2 + q_1^2 <= rho_max q_2^2``: a pair that fails both
``rho3`` and ``rho2`` tests is rejected without a division or an ``exp``.

Layout: the image is cut into ``TILE x TILE`` tiles. Each visible surfel is listed in
every tile of its support box that its conic or low-pass disc reaches (``tile_reached``),
the surfels taken front to back by ``(centre depth, id)`` (one global sort), so each tile's
list comes out in that order. The tiles are dealt to the threads beforehand
(``schedule_tiles``); one thread renders a tile surfel by surfel, touching only the
pixels of the surfel's box inside the tile, with the per-pixel state in small local
arrays.

The forward writes one record per composited pair (pixel and branch flags,
transmittance before it, alpha), grouped by list entry; the backward replays exactly
those pairs - the forward's skips, stop and median choice by construction - and
recomputes each pair's intersection from the entry's ``adj(T)`` (cheaper than storing
it: 3 values per record instead of 7, -8% backward time at 800x600/200k), visiting the
entries in reverse, so each pixel sees its pairs back to front, and writes what a
(tile, surfel) pair receives from all pixels of its tile into that pair's own slot.
The per-surfel sum runs over slots in a fixed order. No atomics, no per-thread
buffers: results are bitwise identical whatever the number of threads or the
scheduling. Memory kept for the backward grows with the pairs (records: the boxes'
pixel count x 3 values, an upper bound; gathered entries and slots: the (tile, surfel)
pairs x (24 + C) and (17 + C) float64).

Arithmetic is float64 inside, but for one rounding: numba types ``float()`` of a float32
as float32, so for float32 surfels the quaternion's squared norm and its root are float32
(in ``preprocess`` and ``reduce_and_chain``). Inputs may be float32 or float64 and outputs,
gradients and pair records take the input dtype. The per-pixel state kept for the backward is
float64.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from pipeline.rasterizer.project import ALPHA_MAX, ALPHA_MIN, RHO_CUT_MAX, T_MIN, UV_MAX

TILE_SHIFT = 4
TILE = 1 << TILE_SHIFT  # a tile's local pixel index (py - y0) * TILE + px - x0 fits the 8 low bits of R_FLAGS
_CHUNK = 256  # surfels per prange iteration of the per-surfel kernels (scratch arrays allocated once)
_BIN_PARTS = 8  # parts of the depth order that bin_tiles counts and fills in parallel (any count gives the same lists)

# Per-surfel geometry (float64) computed by ``preprocess``.
GEO_AX = 0  # 3: T_v x T_w  (q = x AX + y AY + A0)
GEO_AY = 3  # 3: T_w x T_u
GEO_A0 = 6  # 3: T_u x T_v
GEO_DET = 9  # det T
GEO_CX = 10  # projected centre (pixels)
GEO_CY = 11
GEO_RHO_MAX = 12  # min(2 ln(255 o), 9), with rounding slack
GEO_OPACITY = 13
GEO_INV_DET = 14  # 1 / det T (z = det / q2, so 1 / z = q2 / det)
GEO_INV_ZC = 15  # 1 / centre depth (low-pass branch)
GEO_SIZE = 16

# Per (tile, surfel) entry, gathered in list order by ``gather_entries`` so the compositing
# kernels read their surfels' data sequentially (the surfel ids of a tile's list are
# scattered over tens of MB: each entry's loads were cache misses). Columns 0..GEO_SIZE-1
# are the surfel's ``geo`` row; every value is held exactly (float64).
E_ZC = GEO_SIZE  # centre depth (as stored in Tm)
E_NRM = GEO_SIZE + 1  # 3: camera-facing normal
E_BOX = GEO_SIZE + 4  # 4: support box xmin, xmax, ymin, ymax
E_FEAT = GEO_SIZE + 8  # C: features

# Gradient slot per (tile, surfel) pair; linear in the pair terms, so slots are summed
# per surfel before ``_slot_to_dT`` turns them into dL/dT.
S_AX = 0  # 3: dL/dAX = sum x dL/dq
S_AY = 3  # 3: sum y dL/dq
S_A0 = 6  # 3: sum dL/dq
S_DET = 9  # dL/d det
S_CX = 10  # dL/dc (low-pass branch)
S_CY = 11
S_TW2 = 12  # dL/dT_w2 through the centre depth (low-pass branch)
S_OPACITY = 13
S_NORMAL = 14  # 3
S_FEATURE = 17  # C
S_FIXED = 17

# One record per composited (pixel, surfel) pair, written by the forward for the backward.
R_FLAGS = 0  # tile-local pixel index (stride TILE) + 256 * use3 + 512 * capped (exact in float32)
R_T = 1  # transmittance before the pair
R_A = 2  # alpha
R_SIZE = 3

# Per-pixel row of the backward's tile table.
_PX_GA = 0  # dL/dA with the expected depth folded in
_PX_GD = 1  # dL/dD = g_depth / (A + eps)
_PX_GN = 2  # 3: camera-frame normal cotangent with the world normal folded in
_PX_W = 5  # g_dist * W, g_dist * M1, g_dist * M2
_PX_M1 = 6
_PX_M2 = 7
_PX_GMED = 8
_PX_MED = 9  # tile-local list position of the median surfel (-1: none)
_PX_FEAT = 10  # C: feature cotangents

_RHO_SLACK = 1e-6
# The per-pair kernels let LLVM fuse a * b + c into one FMA (no other fast-math freedom:
# no reassociation, so results stay bitwise identical across thread counts): -3% forward,
# -8% backward at 800x600/200k. Set-up and binning stay unfused, so the support boxes are
# the ones project.support_boxes computes.
_CONTRACT = {"contract"}


@njit(inline="always")
def _cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(parallel=True, cache=True, error_model="numpy")
def preprocess(means, quats, scales, opac, K, Rwc, twc, width, height, near, far, Tm, nrm, geo, depth, box, radii,
               centre, round32, reached):  # fmt: skip
    """Per surfel: ``Tm`` (P, 9) ray transform ``K [s_u R_c e_u, s_v R_c e_v, p_c]``
    (row-major), ``nrm`` (P, 3) camera-frame normal facing the camera, ``geo``,
    ``depth`` (centre z), ``box`` (P, 4) support box, ``radii`` (0 = not visible),
    ``centre`` (P, 2) the projected centre in ``Tm``'s dtype (0 where not drawn) and
    ``reached`` the tiles of its box it reaches (:func:`reach_bits`; 0 where not drawn)."""
    fx, sk, cx0, fy, cy0 = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    big = 4.0 * max(width, height)
    for chunk in prange(-(-means.shape[0] // _CHUNK)):
        R = np.empty((3, 3))
        M = np.empty((3, 3))  # camera-frame columns s_u t_u, s_v t_v, p_c
        n = np.empty(3)
        T = np.empty((3, 3))
        for i in range(chunk * _CHUNK, min(means.shape[0], (chunk + 1) * _CHUNK)):
            w, x, y, z = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
            inv = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
            w, x, y, z = w * inv, x * inv, y * inv, z * inv
            R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
            R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
            R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
            for r in range(3):
                M[r, 0] = float(scales[i, 0]) * (Rwc[r, 0] * R[0, 0] + Rwc[r, 1] * R[1, 0] + Rwc[r, 2] * R[2, 0])
                M[r, 1] = float(scales[i, 1]) * (Rwc[r, 0] * R[0, 1] + Rwc[r, 1] * R[1, 1] + Rwc[r, 2] * R[2, 1])
                M[r, 2] = Rwc[r, 0] * means[i, 0] + Rwc[r, 1] * means[i, 1] + Rwc[r, 2] * means[i, 2] + twc[r]
                n[r] = Rwc[r, 0] * R[0, 2] + Rwc[r, 1] * R[1, 2] + Rwc[r, 2] * R[2, 2]
            # Face the camera: n <- -sign(n . p_c) n (dropped when the plane contains the eye).
            d = n[0] * M[0, 2] + n[1] * M[1, 2] + n[2] * M[2, 2]
            sgn = -1.0 if d > 0 else (1.0 if d < 0 else 0.0)
            for r in range(3):
                nrm[i, r] = sgn * n[r]
            for c in range(3):
                T[0, c] = fx * M[0, c] + sk * M[1, c] + cx0 * M[2, c]
                T[1, c] = fy * M[1, c] + cy0 * M[2, c]
                T[2, c] = M[2, c]
            for r in range(3):
                for c in range(3):
                    Tm[i, 3 * r + c] = T[r, c]
            # Round to the storage dtype so the geometry matches what the backward sees.
            for r in range(3):
                for c in range(3):
                    T[r, c] = float(Tm[i, 3 * r + c])
            ax = _cross(T[1, 0], T[1, 1], T[1, 2], T[2, 0], T[2, 1], T[2, 2])
            ay = _cross(T[2, 0], T[2, 1], T[2, 2], T[0, 0], T[0, 1], T[0, 2])
            a0 = _cross(T[0, 0], T[0, 1], T[0, 2], T[1, 0], T[1, 1], T[1, 2])
            zc = T[2, 2]
            depth[i] = zc
            o = float(opac[i])
            rho_cut = min(2.0 * math.log(255.0 * o), RHO_CUT_MAX) if o > 0 else -1.0
            for c in range(3):
                geo[i, GEO_AX + c] = ax[c]
                geo[i, GEO_AY + c] = ay[c]
                geo[i, GEO_A0 + c] = a0[c]
            det = T[2, 0] * a0[0] + T[2, 1] * a0[1] + T[2, 2] * a0[2]
            geo[i, GEO_DET] = det
            geo[i, GEO_INV_DET] = 1.0 / det if det != 0.0 else 0.0  # unused when det == 0 (z = 0 < near)
            geo[i, GEO_INV_ZC] = 1.0 / zc if zc != 0.0 else 0.0
            geo[i, GEO_RHO_MAX] = rho_cut * (1.0 + _RHO_SLACK) + _RHO_SLACK
            geo[i, GEO_OPACITY] = o
            radii[i] = 0
            reached[i] = 0
            box[i, 0], box[i, 1], box[i, 2], box[i, 3] = 0, -1, 0, -1
            if not (zc >= near and zc <= far and rho_cut >= 0.0):
                geo[i, GEO_CX] = 0.0
                geo[i, GEO_CY] = 0.0
                centre[i, 0] = 0.0
                centre[i, 1] = 0.0
                continue
            pcx, pcy = T[0, 2] / zc, T[1, 2] / zc
            geo[i, GEO_CX] = pcx
            geo[i, GEO_CY] = pcy
            centre[i, 0] = pcx
            centre[i, 1] = pcy
            # Support box: image of the disc u^2 + v^2 <= rho_cut through the dual conic
            # T diag(r2, r2, -1) T^T (bounded iff its (2,2) entry < 0), union the low-pass
            # square; see project.support_boxes (the torch twin used by the reference).
            r2 = rho_cut
            c22 = r2 * (T[2, 0] ** 2 + T[2, 1] ** 2) - T[2, 2] ** 2
            d2 = math.sqrt(r2 / 2.0)
            lo_x, hi_x, lo_y, hi_y = -big, big, -big, big
            if c22 < 0:
                c02 = r2 * (T[0, 0] * T[2, 0] + T[0, 1] * T[2, 1]) - T[0, 2] * T[2, 2]
                c12 = r2 * (T[1, 0] * T[2, 0] + T[1, 1] * T[2, 1]) - T[1, 2] * T[2, 2]
                c00 = r2 * (T[0, 0] ** 2 + T[0, 1] ** 2) - T[0, 2] ** 2
                c11 = r2 * (T[1, 0] ** 2 + T[1, 1] ** 2) - T[1, 2] ** 2
                xc, yc = c02 / c22, c12 / c22
                hx = math.sqrt(max(xc * xc - c00 / c22, 0.0))
                hy = math.sqrt(max(yc * yc - c11 / c22, 0.0))
                lo_x, hi_x = min(xc - hx, pcx - d2), max(xc + hx, pcx + d2)
                lo_y, hi_y = min(yc - hy, pcy - d2), max(yc + hy, pcy + d2)
                if not (math.isfinite(lo_x) and math.isfinite(hi_x) and math.isfinite(lo_y) and math.isfinite(hi_y)):
                    lo_x, hi_x, lo_y, hi_y = -big, big, -big, big
            rad = max(max(hi_x - pcx, pcx - lo_x), max(hi_y - pcy, pcy - lo_y))
            xmin = max(int(math.ceil(max(lo_x - 0.5, -1.0))), 0)
            xmax = min(int(math.floor(min(hi_x + 0.5, float(width)))), width - 1)
            ymin = max(int(math.ceil(max(lo_y - 0.5, -1.0))), 0)
            ymax = min(int(math.floor(min(hi_y + 0.5, float(height)))), height - 1)
            if xmin <= xmax and ymin <= ymax:
                box[i, 0], box[i, 1], box[i, 2], box[i, 3] = xmin, xmax, ymin, ymax
                radii[i] = max(1, int(math.ceil(min(max(rad, 0.0), big))))
                reached[i] = reach_bits(xmin, xmax, ymin, ymax, geo[i], round32)


@njit(cache=True)
def break_depth_ties(order, depth):
    """Make ``order`` (surfel ids sorted by ``depth``, any order among equal depths)
    sorted by ``(depth, id)``: each run of equal depths sorted by id (insertion sort for
    the usual short runs; a long one, e.g. a fronto-parallel plane, by ``np.sort``)."""
    n = order.shape[0]
    k = 0
    while k < n:
        e = k + 1
        while e < n and depth[order[e]] == depth[order[k]]:
            e += 1
        if e - k > 32:
            order[k:e] = np.sort(order[k:e])
            k = e
            continue
        for i in range(k + 1, e):
            s = order[i]
            m = i - 1
            while m >= k and order[m] > s:
                order[m + 1] = order[m]
                m -= 1
            order[m + 1] = s
        k = e


# The binning lists a surfel in a tile of its box only where some pixel centre of the tile may
# composite it. rho_max is inflated by this factor there: far beyond the kernels' float32
# rounding of rho, so no entry the kernels would composite (or that would end a pixel) is
# dropped and every result stays bit for bit what the full box gives.
CULL_MARGIN = 1e-3
# Below this det / (s00 s11) the ellipse's centre is ill-conditioned (a surfel seen edge-on):
# the test then tries all four edges of a tile rather than those facing the centre.
_WELL_POSED = 1e-4


@njit(inline="always")
def _geo_value(g, k, round32):
    # np.float64: numba's float() of a float32 stays float32
    return np.float64(np.float32(g[k])) if round32 else np.float64(g[k])


@njit(inline="always")
def tile_conic(g, round32):
    """The per-tile test's constants of one surfel (``g``: its ``geo`` row, rounded to float32
    where ``round32``, as the simd kernels' rows hold it): q's coefficients, the inflated
    ``rho_max`` ``r``, the centre, from the quadratic ``Q(x, y) = q0^2 + q1^2 - r q2^2``
    (``Q <= 0`` where ``rho3 <= r``) ``= s00 x^2 + 2 s01 x y + s11 y^2 + 2 s02 x + 2 s12 y + ...``
    its coefficients ``s01, s02, s12, 1 / s00, 1 / s11``, its minimiser ``(ex, ey)``, whether it
    is an ellipse and whether that minimiser is well-conditioned. The C++ binning computes the
    same values in the same order (no fused multiply-add), so both backends list alike."""
    ax0, ax1, ax2 = _geo_value(g, GEO_AX, round32), _geo_value(g, GEO_AX + 1, round32), _geo_value(g, GEO_AX + 2, round32)
    ay0, ay1, ay2 = _geo_value(g, GEO_AY, round32), _geo_value(g, GEO_AY + 1, round32), _geo_value(g, GEO_AY + 2, round32)
    a00, a01, a02 = _geo_value(g, GEO_A0, round32), _geo_value(g, GEO_A0 + 1, round32), _geo_value(g, GEO_A0 + 2, round32)
    cx, cy = _geo_value(g, GEO_CX, round32), _geo_value(g, GEO_CY, round32)
    r = _geo_value(g, GEO_RHO_MAX, round32) * (1.0 + CULL_MARGIN)
    s00 = ax0 * ax0 + ax1 * ax1 - r * (ax2 * ax2)
    s01 = ax0 * ay0 + ax1 * ay1 - r * (ax2 * ay2)
    s11 = ay0 * ay0 + ay1 * ay1 - r * (ay2 * ay2)
    s02 = ax0 * a00 + ax1 * a01 - r * (ax2 * a02)
    s12 = ay0 * a00 + ay1 * a01 - r * (ay2 * a02)
    det2 = s00 * s11 - s01 * s01
    ellipse = s00 > 0.0 and det2 > 0.0
    ex, ey, inv00, inv11 = 0.0, 0.0, 0.0, 0.0
    if ellipse:
        ex = (s01 * s12 - s11 * s02) / det2
        ey = (s01 * s02 - s00 * s12) / det2
        inv00 = 1.0 / s00
        inv11 = 1.0 / s11
    return (ax0, ax1, ax2, ay0, ay1, ay2, a00, a01, a02, r, cx, cy, s01, s02, s12, inv00, inv11, ex, ey,
            ellipse, det2 > _WELL_POSED * (s00 * s11))  # fmt: skip


@njit(inline="always")
def _conic_value(c, x, y):
    q0 = x * c[0] + y * c[3] + c[6]
    q1 = x * c[1] + y * c[4] + c[7]
    q2 = x * c[2] + y * c[5] + c[8]
    return q0 * q0 + q1 * q1 - c[9] * (q2 * q2)


@njit(inline="always")
def tile_reached(c, xa, xb, ya, yb):
    """Whether a pixel centre of ``[xa, xb] x [ya, yb]`` (the surfel's box in a tile) may pass
    the kernels' ``rho`` test: the low-pass disc ``2 |p - c|^2 <= r`` or the conic ``Q <= 0``
    reaches the rectangle (``c``: :func:`tile_conic`). Where ``Q`` is no ellipse, always."""
    dx = max(max(xa - c[10], 0.0), c[10] - xb)
    dy = max(max(ya - c[11], 0.0), c[11] - yb)
    if 2.0 * (dx * dx + dy * dy) <= c[9] or not c[19]:
        return True
    ex, ey = c[17], c[18]
    if xa <= ex and ex <= xb and ya <= ey and ey <= yb:
        return True
    # Q is strictly convex: off the rectangle its minimum over the rectangle lies on an edge
    # facing (ex, ey) (KKT), at the vertex of that edge's parabola clamped to the edge.
    every = not c[20]
    s01, s02, s12, inv00, inv11 = c[12], c[13], c[14], c[15], c[16]
    if every or ey < ya:
        if _conic_value(c, min(max(-(s01 * ya + s02) * inv00, xa), xb), ya) <= 0.0:
            return True
    if every or ey > yb:
        if _conic_value(c, min(max(-(s01 * yb + s02) * inv00, xa), xb), yb) <= 0.0:
            return True
    if every or ex < xa:
        if _conic_value(c, xa, min(max(-(s01 * xa + s12) * inv11, ya), yb)) <= 0.0:
            return True
    if every or ex > xb:
        if _conic_value(c, xb, min(max(-(s01 * xb + s12) * inv11, ya), yb)) <= 0.0:
            return True
    return False


_ALL_TILES = np.uint64(0xFFFFFFFFFFFFFFFF)


@njit(inline="always")
def _box_tile_reached(c, x0, x1, y0, y1, tx, ty):
    """:func:`tile_reached` for the part of box ``[x0, x1] x [y0, y1]`` in tile ``(tx, ty)``."""
    xa, xb = max(x0, tx * TILE), min(x1, tx * TILE + TILE - 1)
    ya, yb = max(y0, ty * TILE), min(y1, ty * TILE + TILE - 1)
    return tile_reached(c, float(xa), float(xb), float(ya), float(yb))


@njit(inline="always")
def reach_bits(x0, x1, y0, y1, g, round32):
    """The tiles of box ``[x0, x1] x [y0, y1]`` (row-major) that the surfel of ``geo`` row ``g``
    reaches, as bits, for a box of at most 64 tiles (one tile: reached, untested); all bits
    set for a larger box (the binning tests each of its tiles itself)."""
    tx0, tx1, ty0, ty1 = x0 // TILE, x1 // TILE, y0 // TILE, y1 // TILE
    if tx0 == tx1 and ty0 == ty1:
        return np.uint64(1)
    if (tx1 - tx0 + 1) * (ty1 - ty0 + 1) > 64:
        return _ALL_TILES
    conic = tile_conic(g, round32)
    bits = np.uint64(0)
    i = np.uint64(0)
    for ty in range(ty0, ty1 + 1):
        for tx in range(tx0, tx1 + 1):
            if _box_tile_reached(conic, x0, x1, y0, y1, tx, ty):
                bits |= np.uint64(1) << i
            i += np.uint64(1)
    return bits


@njit(inline="always")
def _listed(bits, i, n_box_tiles, x0, x1, y0, y1, tx, ty, g, round32):
    """Whether tile ``i`` (row-major; ``(tx, ty)``) of a box is listed: ``reach_bits``' bit, or
    for a box of more than 64 tiles the test itself."""
    if n_box_tiles <= 64:
        return (bits >> np.uint64(i)) & np.uint64(1) != np.uint64(0)
    return _box_tile_reached(tile_conic(g, round32), x0, x1, y0, y1, tx, ty)


@njit(parallel=True, cache=True, error_model="numpy")
def bin_tiles(front_to_back, box, reached, geo, round32, n_tx, n_ty):
    """List every visible surfel in the tiles of its box that it reaches (``reached``:
    :func:`reach_bits` from :func:`preprocess`; ``geo``, rounded to float32 where ``round32``,
    for boxes of more than 64 tiles), front to back per tile.

    ``front_to_back``: the drawn surfel ids sorted by ``(centre depth, id)``
    (``depth_order``); filling the tiles in that order leaves each tile's list sorted by
    ``(depth, id)`` with no per-tile sort. Returns ``tile_start (n_tiles + 1)``,
    ``tile_list (n_pairs)`` surfel ids, ``emit_start (P + 1)`` and ``slot_of_entry
    (n_pairs)``: the gradient slot of list entry ``j``, such that surfel ``s``'s slots are
    ``emit_start[s]:emit_start[s + 1]``, in its own row-major order of the tiles it reaches
    (the backward scatters each entry's slot there, so the per-surfel sum reads them
    contiguously); and ``rec_tile_start``, each tile's region in the pair-record buffer (its
    entries' box pixels: an upper bound).
    """
    P = box.shape[0]
    n_tiles = n_tx * n_ty
    n = front_to_back.shape[0]
    per_surfel = np.zeros(P + 1, np.int64)
    # Tile ranges, pixel boxes and reached tiles in front-to-back order, so the passes below
    # read them in order (in depth order the ids are scattered: reading ``box[s]`` there
    # missed the cache).
    tiles = np.empty((n, 4), np.int32)
    pix = np.empty((n, 4), np.int32)
    bits = np.empty(n, np.uint64)
    for k in prange(n):
        s = front_to_back[k]
        for c in range(4):
            pix[k, c] = box[s, c]
            tiles[k, c] = box[s, c] // TILE
        bits[k] = reached[s]
    # Counted and filled in parallel over contiguous parts of the front-to-back order: part
    # ``b`` writes its entries of tile ``t`` after those of the parts before it, so each
    # tile's list is in front-to-back order as a sequential fill would leave it. The count
    # also sums each tile's box pixels and each surfel's entries, the fill writes each
    # entry's gradient slot.
    n_parts = _BIN_PARTS
    part_len = -(-n // n_parts)
    part_counts = np.zeros((n_parts, n_tiles), np.int64)
    part_pixels = np.zeros((n_parts, n_tiles), np.int64)
    for b in prange(n_parts):
        for k in range(b * part_len, min(n, (b + 1) * part_len)):
            s = front_to_back[k]
            n_box = (tiles[k, 1] - tiles[k, 0] + 1) * (tiles[k, 3] - tiles[k, 2] + 1)
            i = 0
            for ty in range(tiles[k, 2], tiles[k, 3] + 1):
                rows = min(pix[k, 3], ty * TILE + TILE - 1) - max(pix[k, 2], ty * TILE) + 1
                for tx in range(tiles[k, 0], tiles[k, 1] + 1):
                    if _listed(bits[k], i, n_box, pix[k, 0], pix[k, 1], pix[k, 2], pix[k, 3], tx, ty, geo[s], round32):
                        t = ty * n_tx + tx
                        part_counts[b, t] += 1
                        part_pixels[b, t] += rows * (min(pix[k, 1], tx * TILE + TILE - 1) - max(pix[k, 0], tx * TILE) + 1)
                        per_surfel[s + 1] += 1
                    i += 1
    emit_start = np.cumsum(per_surfel)
    tile_start = np.zeros(n_tiles + 1, np.int64)
    capacity = np.zeros(n_tiles + 1, np.int64)
    for t in range(n_tiles):
        total = 0
        pixels = 0
        for b in range(n_parts):
            total += part_counts[b, t]
            pixels += part_pixels[b, t]
        tile_start[t + 1] = tile_start[t] + total
        capacity[t + 1] = capacity[t] + pixels
    tile_list = np.empty(tile_start[-1], np.int32)
    slot_of_entry = np.empty(tile_start[-1], np.int64)
    for b in prange(n_parts):
        fill = tile_start[:-1].copy()
        for t in range(n_tiles):
            for earlier in range(b):
                fill[t] += part_counts[earlier, t]
        for k in range(b * part_len, min(n, (b + 1) * part_len)):
            s = front_to_back[k]
            slot = emit_start[s]
            n_box = (tiles[k, 1] - tiles[k, 0] + 1) * (tiles[k, 3] - tiles[k, 2] + 1)
            i = 0
            for ty in range(tiles[k, 2], tiles[k, 3] + 1):
                for tx in range(tiles[k, 0], tiles[k, 1] + 1):
                    if _listed(bits[k], i, n_box, pix[k, 0], pix[k, 1], pix[k, 2], pix[k, 3], tx, ty, geo[s], round32):
                        t = ty * n_tx + tx
                        tile_list[fill[t]] = s
                        slot_of_entry[fill[t]] = slot
                        slot += 1
                        fill[t] += 1
                    i += 1
    return tile_start, tile_list, emit_start, slot_of_entry, capacity


@njit(parallel=True, cache=True, error_model="numpy")
def gather_entries(tile_list, geo, Tm, nrm, box, feat, ent):
    """``ent[j]`` = the data of surfel ``tile_list[j]`` that the compositing kernels read
    (see ``E_*``), for every list entry ``j``."""
    C = feat.shape[1]
    n = tile_list.shape[0]
    for chunk in prange(-(-n // _CHUNK)):
        for j in range(chunk * _CHUNK, min(n, (chunk + 1) * _CHUNK)):
            s = tile_list[j]
            for k in range(GEO_SIZE):
                ent[j, k] = geo[s, k]
            ent[j, E_ZC] = float(Tm[s, 8])
            for k in range(3):
                ent[j, E_NRM + k] = float(nrm[s, k])
            for k in range(4):
                ent[j, E_BOX + k] = float(box[s, k])
            for c in range(C):
                ent[j, E_FEAT + c] = float(feat[s, c])


@njit(cache=True)
def schedule_tiles(cost, n_workers):
    """Split the tiles over ``n_workers`` by longest-processing-time-first: tiles by
    decreasing ``cost``, each to the least loaded worker. Returns ``worker_start
    (n_workers + 1)`` and ``worker_tiles``: worker ``k`` renders
    ``worker_tiles[worker_start[k]:worker_start[k + 1]]``, largest first.

    The kernels run one ``prange`` iteration per worker: numba's scheduler splits a
    ``prange`` into contiguous blocks, so a largest-first tile list gave one thread all
    the large tiles (measured: 2 threads barely faster than 1). The split only changes
    which thread renders a tile, never a result.
    """
    n = cost.shape[0]
    order = np.argsort(-cost, kind="mergesort")
    load = np.zeros(n_workers)
    owner = np.empty(n, np.int64)
    counts = np.zeros(n_workers + 1, np.int64)
    for k in range(n):
        w = np.argmin(load)
        load[w] += cost[order[k]]
        owner[k] = w
        counts[w + 1] += 1
    worker_start = np.cumsum(counts)
    fill = worker_start[:-1].copy()
    worker_tiles = np.empty(n, np.int64)
    for k in range(n):
        worker_tiles[fill[owner[k]]] = order[k]
        fill[owner[k]] += 1
    return worker_start, worker_tiles


@njit(inline="always")
def _tile_bounds(t, n_tx, width, height):
    """Pixel range ``[x0, x1) x [y0, y1)`` of tile ``t`` (row-major, ``n_tx`` per row)."""
    ty = t // n_tx
    x0 = (t - ty * n_tx) * TILE
    y0 = ty * TILE
    return x0, y0, min(x0 + TILE, width), min(y0 + TILE, height)


@njit(inline="always", fastmath=_CONTRACT)
def _pair(x, dy2, qr0, qr1, qr2, ax0, ax1, ax2, cx, rho_max, det, inv_det, zc, inv_zc, near, o):
    """One (pixel, surfel) pair: ``(ok, alpha, a_raw, G, z, 1/z, use3, u, v, 1/q2)``.

    ``ok`` is False when the pair is skipped: ``rho`` beyond ``rho_max``, depth below
    ``near`` or ``alpha < 1/255``. The row supplies ``qr = y AY + A0`` and
    ``dy2 = (y - cy)^2``; ``zc`` is the centre depth used by the low-pass branch.
    """
    q0 = x * ax0 + qr0
    q1 = x * ax1 + qr1
    q2 = x * ax2 + qr2
    dx = x - cx
    rho2 = 2.0 * (dx * dx + dy2)
    in3 = abs(q2) * UV_MAX > max(abs(q0), abs(q1)) and q0 * q0 + q1 * q1 <= rho_max * (q2 * q2)
    if not in3 and rho2 > rho_max:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, False, 0.0, 0.0, 0.0
    u = 0.0
    v = 0.0
    inv = 0.0
    use3 = False
    if in3:
        inv = 1.0 / q2
        u = q0 * inv
        v = q1 * inv
        use3 = u * u + v * v <= rho2
    rho = rho2
    z = zc
    iz = inv_zc
    if use3:
        rho = u * u + v * v
        z = det * inv
        iz = q2 * inv_det
    if rho > rho_max or z < near:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, False, 0.0, 0.0, 0.0
    G = math.exp(-0.5 * rho)
    a_raw = o * G
    a = min(ALPHA_MAX, a_raw)
    return a >= ALPHA_MIN, a, a_raw, G, z, iz, use3, u, v, inv


@njit(parallel=True, cache=True, error_model="numpy", fastmath=_CONTRACT)
def forward(
    tile_start, worker_start, worker_tiles, ent, Rwc, width, n_tx, near, far, depth_eps,
    out_feat, out_alpha, out_depth, out_med, out_ncam, out_nworld, out_dist,
    aux_T, aux_D, aux_W, aux_M1, aux_M2, med_local, rec_tile_start, rec, rec_start, rec_count,
):  # fmt: skip
    """Composite every tile front to back.

    Besides the seven maps it keeps, per pixel, the final transmittance ``aux_T``,
    ``D = sum w z``, the moment sums ``W = sum w``, ``M1 = sum w m``, ``M2 = sum w m^2``
    (float64) and the tile-local list position of the median-depth surfel
    (``med_local``, -1 if none); and one record (``R_*``) per composited pair, those of
    list entry ``j`` at ``rec[rec_start[j] : rec_start[j] + rec_count[j]]``. The backward
    replays exactly these pairs.
    """
    height = out_alpha.shape[0]
    C = ent.shape[1] - E_FEAT
    mscale = far / (far - near)
    for wk in prange(worker_start.shape[0] - 1):
        # Per-pixel state of one tile, local index p = (py - y0) * TILE + px - x0.
        Tr = np.empty(TILE * TILE)
        Ws = np.empty(TILE * TILE)
        M1 = np.empty(TILE * TILE)
        M2 = np.empty(TILE * TILE)
        D = np.empty(TILE * TILE)
        med = np.empty(TILE * TILE)
        F = np.empty((TILE * TILE, C))
        N = np.empty((TILE * TILE, 3))
        medi = np.empty(TILE * TILE, np.int32)
        done = np.empty(TILE * TILE, np.bool_)
        fs = np.empty(C)
        for it in range(worker_start[wk], worker_start[wk + 1]):
            t = worker_tiles[it]
            x0, y0, x1, y1 = _tile_bounds(t, n_tx, width, height)
            npx = (x1 - x0) * (y1 - y0)
            Tr[:] = 1.0
            Ws[:] = 0.0
            M1[:] = 0.0
            M2[:] = 0.0
            D[:] = 0.0
            med[:] = 0.0
            F[:] = 0.0
            N[:] = 0.0
            medi[:] = -1
            done[:] = False
            n_done = 0
            start = tile_start[t]
            r = rec_tile_start[t]
            for j in range(start, tile_start[t + 1]):
                rec_start[j] = r
                rec_count[j] = 0
            for j in range(start, tile_start[t + 1]):
                if n_done == npx:
                    break
                rec_start[j] = r
                e = ent[j]
                ax0, ax1, ax2 = e[GEO_AX], e[GEO_AX + 1], e[GEO_AX + 2]
                ay0, ay1, ay2 = e[GEO_AY], e[GEO_AY + 1], e[GEO_AY + 2]
                a00, a01, a02 = e[GEO_A0], e[GEO_A0 + 1], e[GEO_A0 + 2]
                det, cx, cy = e[GEO_DET], e[GEO_CX], e[GEO_CY]
                rho_max, o = e[GEO_RHO_MAX], e[GEO_OPACITY]
                inv_det, inv_zc = e[GEO_INV_DET], e[GEO_INV_ZC]
                zc = e[E_ZC]
                for c in range(C):
                    fs[c] = e[E_FEAT + c]
                n0, n1, n2 = e[E_NRM], e[E_NRM + 1], e[E_NRM + 2]
                bx0, bx1, by0, by1 = int(e[E_BOX]), int(e[E_BOX + 1]), int(e[E_BOX + 2]), int(e[E_BOX + 3])
                for py in range(max(by0, y0), min(by1, y1 - 1) + 1):
                    y = float(py)
                    dy = y - cy
                    dy2 = dy * dy
                    qr0 = y * ay0 + a00
                    qr1 = y * ay1 + a01
                    qr2 = y * ay2 + a02
                    row = (py - y0) * TILE - x0
                    for px in range(max(bx0, x0), min(bx1, x1 - 1) + 1):
                        p = row + px
                        if done[p]:
                            continue
                        ok, a, a_raw, G, z, iz, use3, u, v, inv = _pair(
                            float(px), dy2, qr0, qr1, qr2, ax0, ax1, ax2, cx, rho_max, det, inv_det, zc, inv_zc, near, o
                        )
                        if not ok:
                            continue
                        T = Tr[p]
                        T_next = T * (1.0 - a)
                        if T_next < T_MIN:
                            done[p] = True
                            n_done += 1
                            continue
                        w = a * T
                        for c in range(C):
                            F[p, c] += w * fs[c]
                        N[p, 0] += w * n0
                        N[p, 1] += w * n1
                        N[p, 2] += w * n2
                        D[p] += w * z
                        m = mscale * (1.0 - near * iz)
                        Ws[p] += w
                        M1[p] += w * m
                        M2[p] += w * m * m
                        if T > 0.5:
                            med[p] = z
                            medi[p] = j - start
                        Tr[p] = T_next
                        flags = p + (256 if use3 else 0) + (512 if a_raw >= ALPHA_MAX else 0)
                        rec[r, R_FLAGS] = flags
                        rec[r, R_T] = T
                        rec[r, R_A] = a
                        r += 1
                rec_count[j] = r - rec_start[j]
            for py in range(y0, y1):
                for px in range(x0, x1):
                    p = (py - y0) * TILE + px - x0
                    for c in range(C):
                        out_feat[py, px, c] = F[p, c]
                    for r in range(3):
                        out_ncam[py, px, r] = N[p, r]
                        # n_world = R_wc^T n_cam
                        out_nworld[py, px, r] = Rwc[0, r] * N[p, 0] + Rwc[1, r] * N[p, 1] + Rwc[2, r] * N[p, 2]
                    A = 1.0 - Tr[p]
                    out_alpha[py, px] = A
                    out_depth[py, px] = D[p] / (A + depth_eps)
                    out_med[py, px] = med[p]
                    # sum_{i>j} w_i w_j (m_i - m_j)^2 == W M2 - M1^2 (exact identity, float64).
                    out_dist[py, px] = max(Ws[p] * M2[p] - M1[p] * M1[p], 0.0)
                    aux_T[py, px] = Tr[p]
                    aux_D[py, px] = D[p]
                    aux_W[py, px] = Ws[p]
                    aux_M1[py, px] = M1[p]
                    aux_M2[py, px] = M2[p]
                    med_local[py, px] = medi[p]


@njit(parallel=True, cache=True, error_model="numpy", fastmath=_CONTRACT)
def backward(
    tile_start, slot_of_entry, worker_start, worker_tiles, ent, Rwc, width, n_tx, near, far, depth_eps,
    aux_T, aux_D, aux_W, aux_M1, aux_M2, med_local, rec, rec_start, rec_count,
    g_feat, g_alpha, g_depth, g_med, g_ncam, g_nworld, g_dist, slots,
):  # fmt: skip
    """Pair gradients into ``slots`` (n_pairs, 17 + C; entry ``j``'s at row
    ``slot_of_entry[j]``), from the forward's records.

    Per pixel, back to front over its composited pairs:
    ``dL/da_i = T_i (v_i - B_{i+1})`` with the value behind the pair
    ``B_i = a_i v_i + (1 - a_i) B_{i+1}`` (a convex combination: no division by
    ``1 - a_i``),
    ``v_i = gA + gF.f_i + gD z_i + gN.n_i + gDist dDist/dw_i`` and
    ``dDist/dw_i = m_i^2 W - 2 m_i M1 + M2`` (totals), since ``Dist = W M2 - M1^2``.
    The expected depth ``D / (A + eps)`` and the world normal ``R_wc^T N`` are folded
    into ``gD``, ``gA`` and ``gN`` first. Entries are visited in reverse list order;
    within an entry each pixel appears once, so every pixel sees its pairs back to front.
    """
    height = aux_T.shape[0]
    C = ent.shape[1] - E_FEAT
    mscale = far / (far - near)
    for wk in prange(worker_start.shape[0] - 1):
        B = np.empty(TILE * TILE)
        # Per-pixel cotangents and totals of one tile, one contiguous row per pixel (see _PX_*).
        px_tab = np.empty((TILE * TILE, _PX_FEAT + C))
        gfe = np.empty(C)
        fs = np.empty(C)
        for it in range(worker_start[wk], worker_start[wk + 1]):
            t = worker_tiles[it]
            x0, y0, x1, y1 = _tile_bounds(t, n_tx, width, height)
            B[:] = 0.0
            for py in range(y0, y1):
                for px in range(x0, x1):
                    p = (py - y0) * TILE + px - x0
                    inv = 1.0 / (1.0 - aux_T[py, px] + depth_eps)
                    ge = float(g_depth[py, px])
                    gd = float(g_dist[py, px])
                    px_tab[p, _PX_GD] = ge * inv
                    px_tab[p, _PX_GA] = float(g_alpha[py, px]) - ge * aux_D[py, px] * inv * inv
                    for k in range(3):
                        px_tab[p, _PX_GN + k] = float(g_ncam[py, px, k]) + (
                            Rwc[k, 0] * g_nworld[py, px, 0] + Rwc[k, 1] * g_nworld[py, px, 1] + Rwc[k, 2] * g_nworld[py, px, 2]
                        )
                    px_tab[p, _PX_W] = gd * aux_W[py, px]
                    px_tab[p, _PX_M1] = gd * aux_M1[py, px]
                    px_tab[p, _PX_M2] = gd * aux_M2[py, px]
                    px_tab[p, _PX_GMED] = float(g_med[py, px])
                    px_tab[p, _PX_MED] = float(med_local[py, px])
                    for c in range(C):
                        px_tab[p, _PX_FEAT + c] = float(g_feat[py, px, c])
            start = tile_start[t]
            for j in range(tile_start[t + 1] - 1, start - 1, -1):
                li = j - start
                e = ent[j]
                # Scalar accumulators stay in registers (see S_* for their meaning).
                gax0 = gax1 = gax2 = gay0 = gay1 = gay2 = g00 = g01 = g02 = 0.0
                gdet = gcx = gcy = gtw2 = gop = gn_0 = gn_1 = gn_2 = 0.0
                gfe[:] = 0.0
                cx, cy = e[GEO_CX], e[GEO_CY]
                ax0, ax1, ax2 = e[GEO_AX], e[GEO_AX + 1], e[GEO_AX + 2]
                ay0, ay1, ay2 = e[GEO_AY], e[GEO_AY + 1], e[GEO_AY + 2]
                a00, a01, a02 = e[GEO_A0], e[GEO_A0 + 1], e[GEO_A0 + 2]
                det, inv_det, zc, inv_zc = e[GEO_DET], e[GEO_INV_DET], e[E_ZC], e[GEO_INV_ZC]
                inv_o = 1.0 / e[GEO_OPACITY]
                for c in range(C):
                    fs[c] = e[E_FEAT + c]
                n0, n1, n2 = e[E_NRM], e[E_NRM + 1], e[E_NRM + 2]
                for r in range(rec_start[j], rec_start[j] + rec_count[j]):
                    flags = int(rec[r, R_FLAGS])
                    p = flags & 255
                    px = x0 + (p & (TILE - 1))
                    py = y0 + (p >> TILE_SHIFT)
                    x = float(px)
                    y = float(py)
                    T = float(rec[r, R_T])
                    a = float(rec[r, R_A])
                    use3 = flags & 256
                    # The pair's intersection, recomputed as the forward did (see _pair).
                    z = zc
                    iz = inv_zc
                    u = v = inv = 0.0
                    if use3:
                        q0 = x * ax0 + (y * ay0 + a00)
                        q1 = x * ax1 + (y * ay1 + a01)
                        q2 = x * ax2 + (y * ay2 + a02)
                        inv = 1.0 / q2
                        u = q0 * inv
                        v = q1 * inv
                        z = det * inv
                        iz = q2 * inv_det
                    w = a * T
                    m = mscale * (1.0 - near * iz)
                    gq0, gq1, gq2 = px_tab[p, _PX_GN], px_tab[p, _PX_GN + 1], px_tab[p, _PX_GN + 2]
                    gDp = px_tab[p, _PX_GD]
                    gdW, gdM1 = px_tab[p, _PX_W], px_tab[p, _PX_M1]
                    vsum = px_tab[p, _PX_GA] + gDp * z + gq0 * n0 + gq1 * n1 + gq2 * n2
                    vsum += m * m * gdW - 2.0 * m * gdM1 + px_tab[p, _PX_M2]
                    for c in range(C):
                        gf = px_tab[p, _PX_FEAT + c]
                        vsum += gf * fs[c]
                        gfe[c] += gf * w
                    gn_0 += gq0 * w
                    gn_1 += gq1 * w
                    gn_2 += gq2 * w
                    dL_da = T * (vsum - B[p])
                    B[p] = a * vsum + (1.0 - a) * B[p]
                    dz = gDp * w + 2.0 * w * (m * gdW - gdM1) * mscale * near * iz * iz
                    if px_tab[p, _PX_MED] == li:
                        dz += px_tab[p, _PX_GMED]
                    drho = 0.0
                    if not (flags & 512):  # the cap alpha = 0.99 has zero derivative
                        gop += dL_da * a * inv_o  # dalpha/do = G = alpha / o
                        drho = -0.5 * a * dL_da
                    if use3:
                        # rho = (q0^2 + q1^2) / q2^2, z = det / q2.
                        dq0 = 2.0 * drho * u * inv
                        dq1 = 2.0 * drho * v * inv
                        dq2 = -(2.0 * drho * (u * u + v * v) + dz * z) * inv
                        gax0 += x * dq0
                        gax1 += x * dq1
                        gax2 += x * dq2
                        gay0 += y * dq0
                        gay1 += y * dq1
                        gay2 += y * dq2
                        g00 += dq0
                        g01 += dq1
                        g02 += dq2
                        gdet += dz * inv
                    else:
                        # rho2 = 2 |(x, y) - c|^2, z = centre depth T_w2.
                        gcx -= 4.0 * (x - cx) * drho
                        gcy -= 4.0 * (y - cy) * drho
                        gtw2 += dz
                sl = slot_of_entry[j]
                slots[sl, S_AX], slots[sl, S_AX + 1], slots[sl, S_AX + 2] = gax0, gax1, gax2
                slots[sl, S_AY], slots[sl, S_AY + 1], slots[sl, S_AY + 2] = gay0, gay1, gay2
                slots[sl, S_A0], slots[sl, S_A0 + 1], slots[sl, S_A0 + 2] = g00, g01, g02
                slots[sl, S_DET], slots[sl, S_CX], slots[sl, S_CY], slots[sl, S_TW2] = gdet, gcx, gcy, gtw2
                slots[sl, S_OPACITY] = gop
                slots[sl, S_NORMAL], slots[sl, S_NORMAL + 1], slots[sl, S_NORMAL + 2] = gn_0, gn_1, gn_2
                for c in range(C):
                    slots[sl, S_FEATURE + c] = gfe[c]


@njit(inline="always", fastmath=_CONTRACT)
def _slot_to_dT(g, T, dT):
    """dL/dT (3x3) from summed slot terms (see S_* and the module doc)."""
    Tu0, Tu1, Tu2 = T[0], T[1], T[2]
    Tv0, Tv1, Tv2 = T[3], T[4], T[5]
    Tw0, Tw1, Tw2 = T[6], T[7], T[8]
    gx0, gx1, gx2 = g[S_AX], g[S_AX + 1], g[S_AX + 2]
    gy0, gy1, gy2 = g[S_AY], g[S_AY + 1], g[S_AY + 2]
    g00, g01, g02 = g[S_A0], g[S_A0 + 1], g[S_A0 + 2]
    gdet = g[S_DET]
    # For g . (a x b): d/da = b x g, d/db = g x a. AX = Tv x Tw, AY = Tw x Tu, A0 = Tu x Tv;
    # det = Tu . (Tv x Tw): d/dTu = AX, d/dTv = AY, d/dTw = A0.
    ax = _cross(Tv0, Tv1, Tv2, Tw0, Tw1, Tw2)
    ay = _cross(Tw0, Tw1, Tw2, Tu0, Tu1, Tu2)
    a0 = _cross(Tu0, Tu1, Tu2, Tv0, Tv1, Tv2)
    r1 = _cross(gy0, gy1, gy2, Tw0, Tw1, Tw2)  # Tu from AY
    r2 = _cross(Tv0, Tv1, Tv2, g00, g01, g02)  # Tu from A0
    r3 = _cross(Tw0, Tw1, Tw2, gx0, gx1, gx2)  # Tv from AX
    r4 = _cross(g00, g01, g02, Tu0, Tu1, Tu2)  # Tv from A0
    r5 = _cross(gx0, gx1, gx2, Tv0, Tv1, Tv2)  # Tw from AX
    r6 = _cross(Tu0, Tu1, Tu2, gy0, gy1, gy2)  # Tw from AY
    for c in range(3):
        dT[c] = r1[c] + r2[c] + gdet * ax[c]
        dT[3 + c] = r3[c] + r4[c] + gdet * ay[c]
        dT[6 + c] = r5[c] + r6[c] + gdet * a0[c]
    # Low-pass branch: c = (Tu2, Tv2) / Tw2 and the centre depth Tw2.
    gcx, gcy = g[S_CX], g[S_CY]
    dT[2] += gcx / Tw2
    dT[5] += gcy / Tw2
    dT[8] += g[S_TW2] - (gcx * Tu2 + gcy * Tv2) / (Tw2 * Tw2)


@njit(parallel=True, cache=True, error_model="numpy", fastmath=_CONTRACT)
def reduce_and_chain(
    emit_start, slots, quats, scales, means, Tm, nrm, K, Rwc,
    d_means, d_quats, d_scales, d_opac, d_feat, d_means2d,
):  # fmt: skip
    """Per surfel: sum its slots in a fixed order (deterministic), turn them into
    dL/dT, and chain ``T = K [s_u R_wc r_0, s_v R_wc r_1, R_wc p + t]`` and
    ``n = sign * R_wc r_2`` back to means, quats (through the normalisation) and scales.
    ``d_means2d`` is the gradient w.r.t. a screen translation of the splat,
    ``(dL/dT_u . T_w, dL/dT_v . T_w)``. Writes every row of the outputs."""
    G = slots.shape[1]
    C = d_feat.shape[1]
    for chunk in prange(-(-means.shape[0] // _CHUNK)):
        g = np.zeros(G)
        T = np.empty(9)
        dT = np.empty(9)
        dM = np.empty((3, 3))
        R = np.empty((3, 3))
        dR = np.empty((3, 3))
        for i in range(chunk * _CHUNK, min(means.shape[0], (chunk + 1) * _CHUNK)):
            if emit_start[i] == emit_start[i + 1]:  # never drawn: zero gradients
                d_means[i, :] = 0.0
                d_quats[i, :] = 0.0
                d_scales[i, :] = 0.0
                d_opac[i] = 0.0
                d_feat[i, :] = 0.0
                d_means2d[i, :] = 0.0
                continue
            g[:] = 0.0
            for e in range(emit_start[i], emit_start[i + 1]):
                for k in range(G):
                    g[k] += slots[e, k]
            for k in range(9):
                T[k] = float(Tm[i, k])
            _slot_to_dT(g, T, dT)
            d_means2d[i, 0] = dT[0] * T[6] + dT[1] * T[7] + dT[2] * T[8]
            d_means2d[i, 1] = dT[3] * T[6] + dT[4] * T[7] + dT[5] * T[8]
            d_opac[i] = g[S_OPACITY]
            for c in range(C):
                d_feat[i, c] = g[S_FEATURE + c]
            # dM = K^T dT (M = [s_u c_0, s_v c_1, p_c] in the camera frame).
            for c in range(3):
                dM[0, c] = K[0, 0] * dT[c]
                dM[1, c] = K[0, 1] * dT[c] + K[1, 1] * dT[3 + c]
                dM[2, c] = K[0, 2] * dT[c] + K[1, 2] * dT[3 + c] + dT[6 + c]
            w, x, y, z = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
            qn = math.sqrt(w * w + x * x + y * y + z * z)
            w, x, y, z = w / qn, x / qn, y / qn, z / qn
            R[0, 0], R[0, 1], R[0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
            R[1, 0], R[1, 1], R[1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
            R[2, 0], R[2, 1], R[2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
            # dL/d(world columns r_k) = R_wc^T dL/d(camera columns).
            s0, s1 = float(scales[i, 0]), float(scales[i, 1])
            # The facing sign: n = sign * R_wc r_2, and sign = n . (R_wc r_2).
            sgn = 0.0
            for r in range(3):
                sgn += float(nrm[i, r]) * (Rwc[r, 0] * R[0, 2] + Rwc[r, 1] * R[1, 2] + Rwc[r, 2] * R[2, 2])
            sgn = 1.0 if sgn > 0.5 else (-1.0 if sgn < -0.5 else 0.0)
            ds0 = 0.0
            ds1 = 0.0
            for r in range(3):
                dc0 = Rwc[0, r] * dM[0, 0] + Rwc[1, r] * dM[1, 0] + Rwc[2, r] * dM[2, 0]
                dc1 = Rwc[0, r] * dM[0, 1] + Rwc[1, r] * dM[1, 1] + Rwc[2, r] * dM[2, 1]
                dn = Rwc[0, r] * g[S_NORMAL] + Rwc[1, r] * g[S_NORMAL + 1] + Rwc[2, r] * g[S_NORMAL + 2]
                dR[r, 0] = s0 * dc0
                dR[r, 1] = s1 * dc1
                dR[r, 2] = sgn * dn
                ds0 += dc0 * R[r, 0]
                ds1 += dc1 * R[r, 1]
                d_means[i, r] = Rwc[0, r] * dM[0, 2] + Rwc[1, r] * dM[1, 2] + Rwc[2, r] * dM[2, 2]
            d_scales[i, 0] = ds0
            d_scales[i, 1] = ds1
            dw = 2 * (-z * dR[0, 1] + y * dR[0, 2] + z * dR[1, 0] - x * dR[1, 2] - y * dR[2, 0] + x * dR[2, 1])
            dx = 2 * (y * dR[0, 1] + z * dR[0, 2] + y * dR[1, 0] - 2 * x * dR[1, 1] - w * dR[1, 2]
                      + z * dR[2, 0] + w * dR[2, 1] - 2 * x * dR[2, 2])  # fmt: skip
            dy = 2 * (-2 * y * dR[0, 0] + x * dR[0, 1] + w * dR[0, 2] + x * dR[1, 0] + z * dR[1, 2]
                      - w * dR[2, 0] + z * dR[2, 1] - 2 * y * dR[2, 2])  # fmt: skip
            dz = 2 * (-2 * z * dR[0, 0] - w * dR[0, 1] + x * dR[0, 2] + w * dR[1, 0] - 2 * z * dR[1, 1]
                      + y * dR[1, 2] + x * dR[2, 0] + y * dR[2, 1])  # fmt: skip
            # Through q / |q|: (I - q q^T) / |q|.
            dot = w * dw + x * dx + y * dy + z * dz
            d_quats[i, 0] = (dw - w * dot) / qn
            d_quats[i, 1] = (dx - x * dot) / qn
            d_quats[i, 2] = (dy - y * dot) / qn
            d_quats[i, 3] = (dz - z * dot) / qn
