"""Point sampling of meshes and greedy radius downsampling, as in the public DTU script.

Both are numba kernels: the script's per-triangle Python loop and its per-point
``radius_neighbors`` lists do not scale to millions of points on two cores.
"""
from __future__ import annotations

import zlib

import numba
import numpy as np
from numba import prange

from pipeline.errors import InputError


class MeshError(InputError):
    """A mesh that cannot be evaluated or sampled (empty, degenerate, non-finite)."""


def check_mesh(vertices: np.ndarray, triangles: np.ndarray, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert a triangle mesh; returns ``(float64 (V,3), int64 (F,3))``.

    Raises :class:`MeshError` naming ``name`` for: no vertices, no triangles, wrong shapes,
    non-finite vertices, indices out of range, or no triangle of positive area.
    """
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(triangles)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) == 0:
        raise MeshError(f"{name}: has no vertices (vertex array of shape {V.shape}, expected (V, 3) with V > 0)")
    if F.ndim != 2 or F.shape[1] != 3 or len(F) == 0:
        raise MeshError(f"{name}: has no triangles (face array of shape {F.shape}, expected (F, 3) with F > 0)")
    if not np.issubdtype(F.dtype, np.integer):
        raise MeshError(f"{name}: triangle indices must be integers, got {F.dtype}")
    F = F.astype(np.int64)
    bad = ~np.isfinite(V).all(axis=1)
    if bad.any():
        raise MeshError(f"{name}: {int(bad.sum())} of {len(V)} vertices are not finite (NaN/inf)")
    if F.min() < 0 or F.max() >= len(V):
        raise MeshError(f"{name}: triangle indices out of range [0, {len(V)}) (min {F.min()}, max {F.max()})")
    tri = V[F]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not (area2 > 0).any():
        raise MeshError(f"{name}: degenerate, all {len(F)} triangles have zero area")
    return V, F


@numba.njit(parallel=True, cache=True)
def _grid_counts(n1, n2):
    out = np.zeros(len(n1), np.int64)
    for t in prange(len(n1)):
        a, b = n1[t], n2[t]
        if a <= 0 or b <= 0:  # the script divides by max(n, 1e-7): no sample at all
            continue
        c = 0
        for i in range(a):
            ci = (i + 0.5) / a
            for j in range(b):
                if ci + (j + 0.5) / b < 1.0:
                    c += 1
                else:
                    break
        out[t] = c
    return out


@numba.njit(parallel=True, cache=True)
def _grid_fill(v0, e1, e2, n1, n2, offsets, out):
    for t in prange(len(n1)):
        a, b = n1[t], n2[t]
        if a <= 0 or b <= 0:
            continue
        k = offsets[t]
        for i in range(a):
            ci = (i + 0.5) / a
            for j in range(b):
                cj = (j + 0.5) / b
                if ci + cj >= 1.0:
                    break
                for d in range(3):
                    out[k, d] = e1[t, d] * ci + e2[t, d] * cj + v0[t, d]
                k += 1


def sample_triangles(vertices: np.ndarray, triangles: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Points on every triangle at about ``spacing_mm`` (the DTU script's ``sample_single_tri``).

    For a triangle with edges ``e1 = v1 - v0`` (length l1), ``e2 = v2 - v0`` (l2) and
    ``|e1 x e2| = A2``: ``thr = spacing * sqrt(l1 l2 / A2)``, ``n_k = floor(l_k / thr)``, and the
    samples are ``v0 + e1 (i + .5) / n1 + e2 (j + .5) / n2`` for ``(i + .5)/n1 + (j + .5)/n2 < 1``
    (about one point per ``spacing^2`` of area). Zero-area triangles are skipped. The mesh
    vertices are *not* included (see :func:`sample_mesh`). Returns ``(M, 3)`` float64 (mm).
    """
    V = np.asarray(vertices, dtype=np.float64)
    tri = V[np.asarray(triangles, dtype=np.int64)]
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    l1 = np.linalg.norm(e1, axis=1)
    l2 = np.linalg.norm(e2, axis=1)
    area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
    keep = area2 > 0
    e1, e2, v0, l1, l2, area2 = e1[keep], e2[keep], tri[keep, 0], l1[keep], l2[keep], area2[keep]
    thr = spacing_mm * np.sqrt(l1 * l2 / area2)
    n1 = np.floor(l1 / thr).astype(np.int64)
    n2 = np.floor(l2 / thr).astype(np.int64)
    counts = _grid_counts(n1, n2)
    offsets = np.zeros(len(counts), np.int64)
    np.cumsum(counts[:-1], out=offsets[1:])
    out = np.empty((int(counts.sum()), 3), np.float64)
    _grid_fill(np.ascontiguousarray(v0), np.ascontiguousarray(e1), np.ascontiguousarray(e2), n1, n2, offsets, out)
    return out


def sample_mesh(vertices: np.ndarray, triangles: np.ndarray, spacing_mm: float) -> np.ndarray:
    """All mesh vertices followed by :func:`sample_triangles` points, as the script does."""
    return np.concatenate([np.asarray(vertices, dtype=np.float64), sample_triangles(vertices, triangles, spacing_mm)])


# --- greedy radius downsampling -------------------------------------------------------------


@numba.njit(parallel=True, cache=True)
def _neighbour_rows(ukeys, ustart, column_steps, lo, hi):
    """For each occupied cell ``u`` and each (dx, dy) column ``m``: the point range
    ``[lo, hi)`` of cells ``(x+dx, y+dy, z-1..z+1)`` in the cell-sorted point array.

    ``ukeys`` (U,) are the sorted unique linear cell keys (z fastest), ``ustart`` (U + 1)
    the first point of each cell, ``column_steps`` (9,) the key offset of each column.
    Targets are sorted like ``ukeys``, so each column is one linear merge.
    """
    U = len(ukeys)
    for m in prange(9):
        step = column_steps[m]
        p = 0  # first cell with key >= target - 1
        q = 0  # first cell with key > target + 1
        for u in range(U):
            target = ukeys[u] + step
            while p < U and ukeys[p] < target - 1:
                p += 1
            if q < p:
                q = p
            while q < U and ukeys[q] <= target + 1:
                q += 1
            lo[u, m] = ustart[p]
            hi[u, m] = ustart[q]


@numba.njit(cache=True)
def _greedy(pts, cell_of, rank, lo, hi, r2):
    """Greedy selection in ``rank`` order, resolved in memory (cell) order.

    Point ``i`` is kept iff no neighbour (distance^2 <= r2) of lower rank is kept. That
    is the sequential greedy, but resolving each point on demand (depth-first over its
    undecided lower-rank neighbours) walks the arrays in spatial order instead of jumping
    around in random order, which is several times faster on large clouds.
    """
    n = len(pts)
    state = np.zeros(n, np.uint8)  # 0 undecided, 1 kept, 2 dropped
    stack = np.empty(n, np.int64)
    for i0 in range(n):
        if state[i0] != 0:
            continue
        top = 0
        stack[0] = i0
        while top >= 0:
            i = stack[top]
            c = cell_of[i]
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            ri = rank[i]
            verdict = 1  # kept unless a lower-rank kept neighbour shows up
            pending = -1
            for m in range(9):
                for q in range(lo[c, m], hi[c, m]):
                    if rank[q] >= ri or state[q] == 2:
                        continue
                    dx = pts[q, 0] - x
                    dy = pts[q, 1] - y
                    dz = pts[q, 2] - z
                    if dx * dx + dy * dy + dz * dz <= r2:
                        if state[q] == 1:
                            verdict = 2
                            break
                        pending = q
                if verdict == 2:
                    break
            if verdict == 2:
                state[i] = 2
                top -= 1
            elif pending >= 0:
                top += 1
                stack[top] = pending
            else:
                state[i] = 1
                top -= 1
    return state == 1


def _compress_axis(c: np.ndarray) -> np.ndarray:
    """Renumber occupied cell coordinates keeping adjacency: gaps of 2+ cells become 2."""
    u, inv = np.unique(c, return_inverse=True)
    comp = np.concatenate([[0], np.cumsum(np.minimum(np.diff(u), 2))])
    return comp[inv]


def _cell_keys(P: np.ndarray, cell_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Linear int64 keys of the cells of ``P`` (z fastest) and the grid dims, padded by one
    cell on each side so that neighbour offsets never wrap into another column."""
    cell = np.floor((P - P.min(axis=0)) / cell_mm).astype(np.int64)
    dims = cell.max(axis=0) + 3
    if np.prod(dims.astype(float)) >= 2.0**62:  # far outliers: squeeze the empty space out
        cell = np.stack([_compress_axis(cell[:, d]) for d in range(3)], axis=1)
        dims = cell.max(axis=0) + 3
        if np.prod(dims.astype(float)) >= 2.0**62:
            raise ValueError(f"point cloud too spread out for a {cell_mm} mm grid (occupied extent {dims} cells)")
    cell += 1
    return (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2], dims


def derived_seed(seed: int, purpose: str) -> int:
    """A 64-bit seed for one purpose (e.g. the GT points' thinning order) derived from a
    user seed: different purposes get unrelated random streams from the same seed."""
    state = np.random.SeedSequence([int(seed), zlib.crc32(purpose.encode("utf-8"))]).generate_state(2, np.uint32)
    return int(state[0]) << 32 | int(state[1])


def radius_downsample(points: np.ndarray, radius_mm: float, seed: int | None = 0) -> np.ndarray:
    """Greedy radius downsampling; returns a bool mask over ``points`` of those kept.

    Same result as the DTU script's loop over ``radius_neighbors`` lists for the same
    visiting order: points are visited in a random order (``seed``; the script's order is
    unseeded) and a point is kept iff no point kept before it lies within ``radius_mm``
    (distance ``<=`` radius). Uses a grid of ``radius``-sized cells, so only the 27 cells
    around a point are searched.
    """
    P = np.ascontiguousarray(points, dtype=np.float64)
    n = len(P)
    if n == 0:
        return np.zeros(0, bool)
    if not radius_mm > 0:
        raise ValueError(f"downsampling radius must be > 0 mm, got {radius_mm}")
    order = np.random.default_rng(seed).permutation(n)
    # Cells slightly larger than the radius so that float rounding cannot put a neighbour
    # at exactly ``radius`` two cells away.
    key, dims = _cell_keys(P, radius_mm * (1 + 1e-9))
    by_cell = np.argsort(key)
    ks = key[by_cell]
    new = np.ones(n, bool)
    new[1:] = ks[1:] != ks[:-1]
    ustart = np.append(np.flatnonzero(new), n)
    ukeys = ks[new]
    del ks, key
    cell_of_sorted = np.cumsum(new) - 1
    rank = np.empty(n, np.int64)
    rank[order] = np.arange(n)
    dx, dy = np.divmod(np.arange(9), 3)
    column_steps = ((dx - 1) * dims[1] + (dy - 1)) * dims[2]
    idx_type = np.int32 if n < 2**31 else np.int64  # halves the table for realistic sizes
    lo = np.empty((len(ukeys), 9), idx_type)
    hi = np.empty((len(ukeys), 9), idx_type)
    _neighbour_rows(ukeys, ustart.astype(idx_type), column_steps, lo, hi)
    kept_sorted = _greedy(np.ascontiguousarray(P[by_cell]), cell_of_sorted, rank[by_cell], lo, hi,
                          float(radius_mm) ** 2)
    keep = np.empty(n, bool)
    keep[by_cell] = kept_sorted
    return keep
