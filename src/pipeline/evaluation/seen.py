"""Accuracy and completeness split by how many input views see the surface.

A mesh point ``p`` is charged its distance to the nearest ground-truth point ``q`` (DTU
accuracy); here ``q`` is also asked which input views see it: ``q`` projects inside the
view's image, lies in front of the camera, and nothing of the GT mesh lies on the ray from
the camera more than ``tol_mm`` before it. Points whose ``q`` is seen by >= 2 views are
surface the views triangulate; by 1 view, surface only that view's photometric loss (and the
priors) can place; by none, surface the method invented (or the far side of a thin part).
Accuracy that worsens on the ">= 2" part is drift of well-seen surface, not a guess at
unseen surface. Completeness splits the same way over the GT points themselves: a GT point
seen by >= 2 views that is far from the mesh is a hole in surface the views triangulate; one
seen by none is surface only invention can cover (the 3-view limit leaves it uncovered too).
Needs the GT mesh (synthetic scenes), world mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from pipeline import geometry
from pipeline.raycast import MeshCaster

GROUPS = ("2+", "1", "0")  # seen by >= 2 input views, by exactly 1, by none
VISIBILITY_TOL_MM = 0.1  # GT points lie on the GT mesh to float32 precision; this is far above it


@dataclass
class InputView:
    """An input camera: intrinsics for a ``width x height`` image (integer pixel centres)."""

    K: np.ndarray  # 3x3
    world_to_cam: np.ndarray  # 4x4, world mm -> camera
    width: int
    height: int


def views_seeing(points_mm: np.ndarray, gt_vertices_mm: np.ndarray, gt_triangles: np.ndarray,
                 views: list[InputView], tol_mm: float = VISIBILITY_TOL_MM) -> np.ndarray:
    """How many of ``views`` see each of ``points_mm`` (N, 3), points on the GT surface
    given by the mesh; ``(N,)`` int."""
    caster = MeshCaster(gt_vertices_mm, gt_triangles)
    P = np.asarray(points_mm, np.float64)
    count = np.zeros(len(P), np.int64)
    for v in views:
        uv, z = geometry.project(v.K, v.world_to_cam, P)
        inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < v.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < v.height - 0.5)
        idx = np.flatnonzero(inside)
        if not len(idx):
            continue
        origin = geometry.camera_center(v.world_to_cam)
        d = P[idx] - origin
        length = np.linalg.norm(d, axis=1)
        # The ray stops tol_mm short of the point: a hit on it means something lies in front.
        rays = np.concatenate([np.broadcast_to(origin, d.shape), d * (1 - tol_mm / length)[:, None]], 1)
        blocked = caster.occluded(rays)
        count[idx[~blocked]] += 1
    return count


def accuracy_by_views_seen(data_mm: np.ndarray, gt_points_mm: np.ndarray, gt_vertices_mm: np.ndarray,
                           gt_triangles: np.ndarray, views: list[InputView], max_dist_mm: float) -> dict:
    """Accuracy of the mesh points ``data_mm`` split by :func:`views_seeing` of their nearest
    GT point: per group of :data:`GROUPS`, ``fraction`` of the points and ``accuracy_mm``
    (mean distance of those within ``max_dist_mm``, as DTU accuracy; NaN for an empty
    group)."""
    if not len(data_mm):
        return {g: {"fraction": math.nan, "accuracy_mm": math.nan} for g in GROUPS}
    dist, nearest = cKDTree(gt_points_mm).query(data_mm, k=1, workers=-1)
    seen = views_seeing(gt_points_mm[nearest], gt_vertices_mm, gt_triangles, views)
    return _split(dist, seen, max_dist_mm, "accuracy_mm")


def completeness_by_views_seen(gt_points_mm: np.ndarray, distance_mm: np.ndarray, gt_vertices_mm: np.ndarray,
                               gt_triangles: np.ndarray, views: list[InputView], max_dist_mm: float) -> dict:
    """Completeness split by :func:`views_seeing` of the GT points themselves:
    ``distance_mm[i]`` is GT point ``i``'s distance to the mesh (``inf`` beyond the search
    radius). Per group of :data:`GROUPS`: ``fraction`` of the GT points and
    ``completeness_mm`` (mean distance of those within ``max_dist_mm``, as DTU completeness;
    NaN for an empty group)."""
    if len(gt_points_mm) != len(distance_mm):
        raise ValueError(f"completeness_by_views_seen: {len(gt_points_mm)} GT points but {len(distance_mm)} distances")
    if not len(gt_points_mm):
        return {g: {"fraction": math.nan, "completeness_mm": math.nan} for g in GROUPS}
    seen = views_seeing(gt_points_mm, gt_vertices_mm, gt_triangles, views)
    return _split(np.asarray(distance_mm, np.float64), seen, max_dist_mm, "completeness_mm")


def _split(dist: np.ndarray, seen: np.ndarray, max_dist_mm: float, key: str) -> dict:
    """Per group of :data:`GROUPS`: the share of ``dist`` in it and its mean below ``max_dist_mm``."""
    groups = {"2+": seen >= 2, "1": seen == 1, "0": seen == 0}
    out = {}
    for g in GROUPS:
        d = dist[groups[g]]
        d = d[d < max_dist_mm]
        out[g] = {"fraction": float(groups[g].mean()), key: float(d.mean()) if len(d) else math.nan}
    return out


def load_input_views(scene_dir, view_ids) -> list[InputView]:
    """The input cameras of a DTU-layout scene, at its stored image size."""
    from pipeline.data import dtu

    cams = dtu.load_cameras(scene_dir)
    width, height = dtu.stored_image_size(scene_dir)
    missing = [v for v in view_ids if v not in cams.K]
    if missing:
        raise dtu.SceneError(f"{cams.path}: no camera for input view(s) {missing}")
    return [InputView(cams.K[v], cams.world_to_cam[v], width, height) for v in view_ids]
