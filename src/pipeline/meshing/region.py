"""The object's region for captures without masks (docs/inputs.md, "Without masks").

Masks keep the background and the table out of the mesh; without them a bounding region
does: the scene's unit sphere (from ``scale_mat``, the sparse points or the cameras:
:mod:`pipeline.data.capture`) and, when the fused depth has one, the half-space above the
support plane (the table the object stands on) shifted up by a margin. The plane is
the dominant plane of the depth points (RANSAC, seeded), taken only when it carries a
large share of them and every camera looks at it from the same side, the side the rest
of the points lie on. With a table, the region is also cut sideways to the object's
footprint: the convex hull (in the table's plane) of the points just above the table
(the object's base, in clusters that are not isolated specks), its edges pushed out by
``footprint_margin_mm`` (overhangs). Without it, repetitive table texture far behind the
object, matched wrongly inside the sphere, would stay in the mesh as floaters.

Frame and units: world frame, mm (lengths of a capture without a unit are in its units).
A plane is ``(n, d)`` with ``|n| = 1``; a point ``x`` is above it when ``n . x + d > 0``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline import geometry
from pipeline.config.mesh import MeshConfig


@dataclass
class Region:
    centre_mm: np.ndarray  # (3,) sphere centre, world mm
    radius_mm: float
    plane: np.ndarray | None = None  # (4,) n, d (world mm): kept where n . x + d > margin_mm
    margin_mm: float = 0.0
    # The footprint: half-planes a . (x - o) + b <= footprint_margin_mm in the table's 2D frame
    # (origin o, axes ``plane_axes``), the rows of a 2D convex hull's equations.
    footprint: np.ndarray | None = None  # (E, 3) rows a_x, a_y, b
    plane_axes: np.ndarray | None = None  # (2, 3) orthonormal axes in the plane
    footprint_margin_mm: float = 0.0

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        """``(M,)`` bool: inside the sphere and, with a plane, more than ``margin_mm`` above it
        (and inside the pushed-out footprint when there is one)."""
        p = np.asarray(points_mm, np.float64)
        ok = np.linalg.norm(p - self.centre_mm, axis=-1) <= self.radius_mm
        if self.plane is not None:
            ok &= p @ self.plane[:3] + self.plane[3] > self.margin_mm
        if self.footprint is not None:
            xy = p @ self.plane_axes.T
            ok &= (xy @ self.footprint[:, :2].T + self.footprint[:, 2]).max(axis=-1) <= self.footprint_margin_mm
        return ok

    def facts(self) -> dict:
        return {"sphere_centre_mm": [round(float(x), 3) for x in self.centre_mm], "sphere_radius_mm": round(self.radius_mm, 3),
                "support_plane": None if self.plane is None else [round(float(x), 6) for x in self.plane],
                "plane_margin_mm": round(self.margin_mm, 3),
                "footprint_edges": 0 if self.footprint is None else len(self.footprint),
                "footprint_margin_mm": round(self.footprint_margin_mm, 3)}


def fit_plane_ransac(points: np.ndarray, inlier_mm: float, iterations: int = 300,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The plane with the most points within ``inlier_mm`` (RANSAC over random triples,
    seeded so the same points give the same plane), refined by least squares on its
    inliers. Returns ``(plane (4,), inlier mask)``."""
    p = np.asarray(points, np.float64)
    if len(p) < 3:
        raise ValueError(f"a plane needs at least 3 points, got {len(p)}")
    rng = np.random.default_rng(seed)
    best, best_count = None, -1
    for _ in range(iterations):
        a, b, c = p[rng.choice(len(p), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n /= norm
        count = int((np.abs((p - a) @ n) < inlier_mm).sum())
        if count > best_count:
            best, best_count = np.append(n, -n @ a), count
    if best is None:
        raise ValueError("every sampled triple of points is collinear: no plane")
    inliers = np.abs(p @ best[:3] + best[3]) < inlier_mm
    centroid = p[inliers].mean(axis=0)
    n = np.linalg.svd(p[inliers] - centroid, full_matrices=False)[2][-1]
    plane = np.append(n, -n @ centroid)
    return plane, np.abs(p @ plane[:3] + plane[3]) < inlier_mm


def support_plane(points_mm: np.ndarray, camera_centres_mm: np.ndarray, inlier_mm: float,
                  min_share: float) -> tuple[np.ndarray | None, dict]:
    """The table under the object, if the points show one: the RANSAC plane of
    ``points_mm`` when at least ``min_share`` of them lie on it, every camera is on one
    side of it and most of the other points are on that side too. Oriented so the cameras
    are above it. Returns ``(plane or None, facts)``."""
    plane, inliers = fit_plane_ransac(points_mm, inlier_mm)
    share = float(inliers.mean())
    side = camera_centres_mm @ plane[:3] + plane[3]
    if np.all(side < 0):
        plane, side = -plane, -side
    rest = points_mm[~inliers] @ plane[:3] + plane[3]
    above = float((rest > 0).mean()) if len(rest) else 0.0
    facts = {"plane_share": round(share, 4), "cameras_above": bool(np.all(side > 0)), "rest_above": round(above, 4)}
    if share < min_share or not np.all(side > 0) or above < 0.5:
        return None, facts
    return plane, facts


def depth_points_mm(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray) -> np.ndarray:
    """World points (mm) of every pixel with depth (> 0) of ``(N, H, W)`` depth maps
    (camera z, integer pixel centres), concatenated over the views."""
    out = [geometry.backproject_depth(Ki, T, d)[d > 0] for d, Ki, T in zip(depths_mm, K, world_to_cam)]
    return np.concatenate(out) if out else np.zeros((0, 3))


def crop_depths(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, region: Region) -> np.ndarray:
    """The depth maps with 0 (no depth) wherever the pixel's point is outside ``region``."""
    out = np.array(depths_mm, np.float64, copy=True)
    for d, Ki, T in zip(out, K, world_to_cam):
        has = d > 0
        d[has & ~region.contains(geometry.backproject_depth(Ki, T, d))] = 0.0
    return out


PLANE_SAMPLE = 100_000  # depth points the table's RANSAC looks at (seeded subsample)
FOOTPRINT_BAND = (2.0, 8.0)  # the object's base: heights above the table, in plane margins
FOOTPRINT_MARGIN = 0.2  # the footprint's edges pushed out by this many unit-sphere radii (overhangs)
MIN_CLUSTER_SHARE = 0.01  # base clusters smaller than this share of the band's points are specks


def plane_axes(normal: np.ndarray) -> np.ndarray:
    """``(2, 3)`` orthonormal axes spanning the plane of unit ``normal``."""
    a = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(normal, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(normal, u)])


def footprint_hull(points_mm: np.ndarray, plane: np.ndarray, margin_mm: float,
                   cluster_mm: float) -> tuple[np.ndarray | None, np.ndarray, dict]:
    """The object's footprint on the table: the 2D convex hull (``(E, 3)`` half-planes, see
    :class:`Region`) of the points in the band :data:`FOOTPRINT_BAND` x ``margin_mm`` above
    ``plane``, after dropping clusters (DBSCAN, ``cluster_mm``) smaller than
    :data:`MIN_CLUSTER_SHARE` of them. ``None`` when too few points are left."""
    import open3d as o3d
    from scipy.spatial import ConvexHull

    axes = plane_axes(plane[:3])
    h = points_mm @ plane[:3] + plane[3]
    band = points_mm[(h > FOOTPRINT_BAND[0] * margin_mm) & (h < FOOTPRINT_BAND[1] * margin_mm)]
    facts = {"footprint_band_points": len(band)}
    if len(band) < 10:
        return None, axes, facts
    labels = np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(band)).cluster_dbscan(
        eps=cluster_mm, min_points=10))
    ids, counts = np.unique(labels[labels >= 0], return_counts=True)
    kept = ids[counts >= max(10, MIN_CLUSTER_SHARE * len(band))]
    base = band[np.isin(labels, kept)] @ axes.T
    facts["footprint_points"] = len(base)
    if len(base) < 10:
        return None, axes, facts
    return ConvexHull(base).equations, axes, facts


def region_for_depths(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, norm_to_world: np.ndarray,
                      voxel_mm: float, plane_share: float, plane_margin_mm: float) -> tuple[Region, dict]:
    """The bounding region of a scene fused without masks: its unit sphere (``norm_to_world``)
    and, when the depth points inside it show a support plane, the half-space
    ``plane_margin_mm`` above it. The plane's inliers lie within 2 voxels of it."""
    sphere = Region(centre_mm=norm_to_world[:3, 3].astype(np.float64), radius_mm=float(norm_to_world[0, 0]))
    pts = depth_points_mm(depths_mm, K, world_to_cam)
    pts = pts[sphere.contains(pts)]
    if len(pts) > PLANE_SAMPLE:
        pts = pts[np.random.default_rng(0).choice(len(pts), PLANE_SAMPLE, replace=False)]
    if len(pts) < 3:
        return sphere, {"plane_share": 0.0}
    centres = np.stack([geometry.camera_center(T) for T in world_to_cam])
    plane, facts = support_plane(pts, centres, 2.0 * voxel_mm, plane_share)
    if plane is None:
        return sphere, facts
    # Clusters link points within 3 voxels or 3 pixels' footprints at the object, the larger.
    pixel_mm = float(np.median([np.linalg.norm(c - sphere.centre_mm) / Ki[0, 0] for c, Ki in zip(centres, K)]))
    hull, axes, hull_facts = footprint_hull(pts, plane, plane_margin_mm, 3.0 * max(voxel_mm, pixel_mm))
    return Region(sphere.centre_mm, sphere.radius_mm, plane, plane_margin_mm, hull, axes,
                  FOOTPRINT_MARGIN * sphere.radius_mm if hull is not None else 0.0), {**facts, **hull_facts}


def crop_mesh_vertices(vertices_mm: np.ndarray, triangles: np.ndarray, region: Region) -> np.ndarray:
    """The triangles with every vertex inside ``region``."""
    inside = region.contains(vertices_mm)
    return triangles[inside[triangles].all(axis=1)]


def cut_to_region(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, norm_to_world: np.ndarray,
                  cfg: MeshConfig, masked: bool) -> tuple[np.ndarray, Region | None, dict]:
    """``cfg.region`` applied to depth maps about to be fused: with ``auto``, only when no
    mask has cut them (``masked`` False). Returns the depth maps (cut or as given), the
    region (``None`` when not applied) and facts for the stage's JSON."""
    if cfg.region == "off" or (cfg.region == "auto" and masked):
        return depths_mm, None, {"region": None}
    scale = float(norm_to_world[0, 0])
    voxel_mm, _ = cfg.sizes_mm(scale)
    region, facts = region_for_depths(depths_mm, K, world_to_cam, norm_to_world, voxel_mm, cfg.region_plane_share,
                                      cfg.region_plane_margin_norm * scale)
    cut = crop_depths(depths_mm, K, world_to_cam, region)
    facts = {"region": {**region.facts(), **facts, "depth_pixels_cut": int((depths_mm > 0).sum() - (cut > 0).sum())}}
    return cut, region, facts
