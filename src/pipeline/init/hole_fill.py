"""Enclosed holes of a depth map, filled by harmonic interpolation (docs/init.md, step 7b).

Why: where a surface is plain and its shading has no gradient (the brightest point of a
Lambertian dome), no window can be matched and the MVS depth has a hole, surrounded by good
depth. Training gets no surfels there, densification fills the hole from its border, and
nothing photometric constrains their depth: on synth_textureless they settled 3 mm in front
of the surface. A membrane stretched over the hole's border (the harmonic interpolant: each
pixel the mean of its four neighbours) is the smoothest guess the border allows.

A hole is *enclosed* when every pixel around it (its 8-neighbours outside it) has depth, and,
given a mask, lies inside the mask: a gap that reaches the silhouette, the image border or
another gap is not filled (its far side is unknown). It is filled only when the 3D points
around it lie near a plane (:func:`flat_rimmed`): a gap between two surfaces at different
depths (a slot between fins, seen through) has a rim that steps, and a membrane over it would
be a surface that is not there. A slot between two fins whose front edges are level has a flat
rim too, and so has a recess behind an occluding edge; another view sees through the first
and sees the occluder in front of the second. A hole is left open when any other view's depth
disagrees with a filled point (:func:`contradicted`); a hole no other view has depth for (a
plain patch all views fail to match) is filled.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.linalg import spsolve

from pipeline import geometry

_EIGHT = np.ones((3, 3), bool)


def enclosed_holes(valid: np.ndarray, max_px: int, mask: np.ndarray | None = None) -> np.ndarray:
    """``(H, W)`` bool: the pixels of every 8-connected region of ``~valid`` (inside ``mask``
    when given) of at most ``max_px`` pixels whose surrounding pixels all have depth and lie
    inside the image (and the mask)."""
    valid = np.asarray(valid, bool)
    if mask is not None and mask.shape != valid.shape:
        raise ValueError(f"enclosed_holes: mask {mask.shape} and valid {valid.shape} differ in shape")
    inside = np.ones_like(valid) if mask is None else np.asarray(mask, bool)
    candidates = ~valid & inside
    out = np.zeros_like(valid)
    if max_px <= 0 or not candidates.any():
        return out
    for box, comp, ring, at_border in _regions(candidates):
        # At the image border its surroundings are not all seen.
        if not at_border and comp.sum() <= max_px and (valid[box] & inside[box])[ring].all():
            out[box] |= comp
    return out


def _regions(pixels: np.ndarray):
    """Each 8-connected region of ``pixels``: ``(box, comp, ring, at_border)``, with ``box``
    its bounding box grown by one pixel (cut at the image), ``comp`` and ``ring`` (its
    8-neighbours outside it) as masks of the box, and whether it touches the image border."""
    labels, _ = ndimage.label(pixels, structure=_EIGHT)
    H, W = pixels.shape
    for k, (ys, xs) in enumerate(ndimage.find_objects(labels), start=1):
        at_border = ys.start == 0 or xs.start == 0 or ys.stop == H or xs.stop == W
        box = (slice(max(ys.start - 1, 0), min(ys.stop + 1, H)), slice(max(xs.start - 1, 0), min(xs.stop + 1, W)))
        comp = labels[box] == k
        yield box, comp, ndimage.binary_dilation(comp, _EIGHT) & ~comp, at_border


def harmonic_fill(depth_mm: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """``depth_mm`` (float64) with the ``holes`` pixels replaced by the solution of Laplace's
    equation (4-neighbour stencil) whose boundary values are the depth around them. Every
    4-neighbour of a hole pixel must be a hole pixel or have depth (``enclosed_holes``
    guarantees it)."""
    z = np.asarray(depth_mm, np.float64).copy()
    holes = np.asarray(holes, bool)
    if z.shape != holes.shape:
        raise ValueError(f"harmonic_fill: depth {z.shape} and holes {holes.shape} differ in shape")
    if not holes.any():
        return z
    H, W = z.shape
    rows, cols = np.nonzero(holes)
    if rows.min() == 0 or cols.min() == 0 or rows.max() == H - 1 or cols.max() == W - 1:
        raise ValueError("harmonic_fill: a hole touches the image border (no boundary value there)")
    index = np.full((H, W), -1, np.int64)
    index[rows, cols] = np.arange(len(rows))
    n = len(rows)
    A_rows, A_cols, A_vals = [np.arange(n)], [np.arange(n)], [np.full(n, 4.0)]
    b = np.zeros(n)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        nr, nc = rows + dy, cols + dx
        j = index[nr, nc]
        inner = j >= 0
        A_rows.append(np.arange(n)[inner])
        A_cols.append(j[inner])
        A_vals.append(np.full(inner.sum(), -1.0))
        boundary = z[nr[~inner], nc[~inner]]
        if np.any(boundary <= 0):
            raise ValueError("harmonic_fill: a hole pixel has a neighbour with no depth that is not in the hole")
        np.add.at(b, np.arange(n)[~inner], boundary)
    A = sparse.csr_matrix((np.concatenate(A_vals), (np.concatenate(A_rows), np.concatenate(A_cols))), shape=(n, n))
    z[rows, cols] = spsolve(A.tocsc(), b)
    return z


def flat_rimmed(holes: np.ndarray, points: np.ndarray, max_bend: float) -> np.ndarray:
    """The regions of ``holes`` (8-connected) whose rim, the ``(H, W, 3)`` ``points`` of the
    pixels around them, lies within ``max_bend`` x the rim's extent of its least-squares
    plane (extent: the largest distance between two rim points, bounded by twice the largest
    distance from their centroid)."""
    holes = np.asarray(holes, bool)
    if points.shape != holes.shape + (3,):
        raise ValueError(f"flat_rimmed: points {points.shape} do not match holes {holes.shape} x 3")
    out = np.zeros_like(holes)
    for box, comp, ring, _ in _regions(holes):
        P = points[box][ring].astype(np.float64)
        if len(P) < 3 or not np.isfinite(P).all():
            continue
        Q = P - P.mean(0)
        extent = 2.0 * np.sqrt((Q**2).sum(1).max())
        normal = np.linalg.svd(Q, full_matrices=False)[2][-1]
        if np.abs(Q @ normal).max() <= max_bend * extent:
            out[box] |= comp
    return out


def contradicted(points_mm: np.ndarray, depths_mm: list[np.ndarray], K: np.ndarray, world_to_cam: np.ndarray,
                 rel_tol: float) -> np.ndarray:
    """``(N,)`` bool: for world points ``points_mm``, whether some view's depth map (camera z,
    mm, 0 = none; ``K`` and ``world_to_cam`` per view) has depth at the point's pixel that
    differs from the point's depth by more than ``rel_tol`` x it: behind it (the view sees
    past the point) or in front (the view sees something else where the point would be)."""
    P = np.asarray(points_mm, np.float64)
    out = np.zeros(len(P), bool)
    for d, Kv, T in zip(depths_mm, K, world_to_cam):
        uv, z = geometry.project(Kv, T, P)
        H, W = d.shape
        with np.errstate(invalid="ignore"):
            u, v = np.round(uv[:, 0]), np.round(uv[:, 1])
        inside = (z > 0) & np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        idx = np.flatnonzero(inside)
        seen = d[v[idx].astype(np.int64), u[idx].astype(np.int64)]
        out[idx] |= (seen > 0) & (np.abs(seen - z[idx]) > rel_tol * z[idx])
    return out
