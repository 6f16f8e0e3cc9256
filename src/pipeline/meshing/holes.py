"""Closing small holes in a fused mesh where the depth maps it was fused from support it.

A TSDF mesh of three views has small holes inside surfaces the views see well, mostly at
steps in depth: the edge between a surface and one behind it, whose wall the views see
end-on, forms no zero crossing (docs/optimize.md, "Holes in the mesh"). Each hole whose boundary loop fits
in a sphere of radius ``radius_mm`` is triangulated (VTK's fill-holes filter, through
Open3D; no vertex is added). A new triangle is kept only where the depth maps agree with
it: at each of its sample points (:data:`SAMPLE_BARYCENTRIC`) some view's depth lies within
``tau_mm`` of the point along that view's ray, and no view sees through it (its depth more
than ``tau_mm`` behind the point, or the point outside that view's mask). A window recess
capped flat, or a gap between two parts, is seen through and stays open.

Units: world mm; depth maps are camera z in mm (0 = none), pixels have integer centres.
"""
from __future__ import annotations

import numpy as np

from pipeline import geometry

# Where a new triangle is tested: its centroid, three points towards its corners and its
# edge midpoints (barycentric weights of the corners).
SAMPLE_BARYCENTRIC = np.array([[1 / 3, 1 / 3, 1 / 3], [0.6, 0.2, 0.2], [0.2, 0.6, 0.2], [0.2, 0.2, 0.6],
                               [0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]])


def depth_support(points_mm: np.ndarray, depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
                  masks: np.ndarray | None, tau_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """``(supported, seen_through)``, ``(P,)`` bool each, for world points ``points_mm``
    ``(P, 3)`` against depth maps ``depths_mm`` ``(N, H, W)`` (camera z, 0 = none) of cameras
    ``K`` ``(N, 3, 3)``, ``world_to_cam`` ``(N, 4, 4)``. A point is read at the pixel nearest
    its projection (integer centres) in each view it projects into, in front of the camera:
    supported where some view's depth there is within ``tau_mm`` of its camera z; seen through
    where some view's depth is more than ``tau_mm`` behind it, or where it falls outside the
    mask of a view that has one (``masks``: ``(M, H, W)`` bool for the first ``M <= N`` views,
    or ``None``)."""
    N, H, W = depths_mm.shape
    supported = np.zeros(len(points_mm), bool)
    seen_through = np.zeros(len(points_mm), bool)
    for i in range(N):
        px, z = geometry.project(K[i], world_to_cam[i], points_mm)
        u, v = np.rint(px[:, 0]), np.rint(px[:, 1])
        inside = (u >= 0) & (u < W) & (v >= 0) & (v < H) & (z > 0)
        ui, vi = u[inside].astype(np.int64), v[inside].astype(np.int64)
        d, zi = depths_mm[i][vi, ui], z[inside]
        through = (d > 0) & (zi < d - tau_mm)
        if masks is not None and i < len(masks):
            through |= ~masks[i][vi, ui]
        seen_through[inside] |= through
        supported[inside] |= (d > 0) & (np.abs(zi - d) <= tau_mm)
    return supported, seen_through


def _new_triangles(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Rows of ``after`` (T', 3) that are no triangle of ``before`` (same vertex set, any
    rotation of the indices)."""
    def keys(F: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.sort(F, axis=1)).view(np.dtype((np.void, 3 * F.dtype.itemsize))).ravel()

    return after[~np.isin(keys(after.astype(np.int64)), keys(before.astype(np.int64)))]


def fill_supported_holes(vertices_mm: np.ndarray, triangles: np.ndarray, depths_mm: np.ndarray, K: np.ndarray,
                         world_to_cam: np.ndarray, masks: np.ndarray | None, radius_mm: float,
                         tau_mm: float) -> tuple[np.ndarray, dict]:
    """The triangles of the mesh ``(vertices_mm, triangles)`` followed by those that close
    its holes of boundary radius up to ``radius_mm`` where the depth maps support them
    (module docstring; :func:`depth_support` at each sample point). Returns the triangles
    and facts: ``hole_triangles`` (new ones proposed), ``hole_triangles_kept``."""
    import open3d as o3d

    F = np.asarray(triangles, np.int64)
    if radius_mm <= 0 or len(F) == 0:
        return F, {"hole_triangles": 0, "hole_triangles_kept": 0}
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor(np.ascontiguousarray(vertices_mm, np.float64))
    mesh.triangle.indices = o3d.core.Tensor(np.ascontiguousarray(F))
    filled = mesh.fill_holes(hole_size=float(radius_mm))
    V_out = filled.vertex.positions.numpy()
    if len(V_out) != len(vertices_mm) or not np.array_equal(V_out, vertices_mm):
        raise RuntimeError("fill_supported_holes: Open3D's fill_holes moved or added vertices")
    new = _new_triangles(F, filled.triangle.indices.numpy().copy())
    if len(new) == 0:
        return F, {"hole_triangles": 0, "hole_triangles_kept": 0}
    points = np.einsum("kc,tcd->tkd", SAMPLE_BARYCENTRIC, np.asarray(vertices_mm, np.float64)[new]).reshape(-1, 3)
    supported, through = depth_support(points, depths_mm, K, world_to_cam, masks, tau_mm)
    keep = (supported & ~through).reshape(len(new), -1).all(axis=1)
    return np.concatenate([F, new[keep]]), {"hole_triangles": int(len(new)), "hole_triangles_kept": int(keep.sum())}
