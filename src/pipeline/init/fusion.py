"""Depth maps -> one point cloud: geometric consistency, averaging, voxel downsampling,
normals.

Geometric consistency (as in MVSNet/COLMAP fusion): a reference pixel with depth ``d``
back-projects to ``X``; ``X`` projects into another view ``s``, whose depth at the nearest
pixel back-projects to ``X_s``; ``X_s`` projected back into the reference must land
within ``px`` pixels of the start and at a depth within ``rel_depth * d`` of ``d``.
A pixel is kept when at least ``min_views`` other views agree; its point is the mean of
``X`` and the agreeing ``X_s`` (which averages out part of the matching noise).

Frames and units: depth maps are camera z in mm, points world mm.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline import geometry
from pipeline.config.init import ConsistencyConfig
from pipeline.geometry import voxel_downsample
from pipeline.init.io import PointCloud


@dataclass
class ViewPoints:
    """Consistent pixels of one view and their fused points."""

    valid: np.ndarray  # (H, W) bool, passed the consistency test
    count: np.ndarray  # (H, W) int, number of agreeing other views
    points_mm: np.ndarray  # (M, 3) world, mean of the agreeing back-projections
    colors: np.ndarray  # (M, 3) mean colour over the agreeing views
    pixels: np.ndarray  # (M, 2) int (row, col) in this view


def check_consistency(depths: np.ndarray, valid: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
                      images: np.ndarray, params: ConsistencyConfig) -> list[ViewPoints]:
    """Geometric consistency of ``(N, H, W)`` depth maps (mm) against each other."""
    N, H, W = depths.shape
    cam_to_world = np.stack([geometry.rigid_inverse(T) for T in world_to_cam])
    out = []
    for r in range(N):
        rows, cols = np.nonzero(valid[r])
        d = depths[r, rows, cols].astype(np.float64)
        rays = geometry.pixel_rays(K[r], cols, rows)
        X = (rays * d[:, None]) @ cam_to_world[r, :3, :3].T + cam_to_world[r, :3, 3]
        acc = X.copy()
        col_acc = images[r, rows, cols].astype(np.float64)
        count = np.zeros(len(d), np.int64)
        for s in range(N):
            if s == r:
                continue
            px, _ = geometry.project(K[s], world_to_cam[s], X)
            with np.errstate(invalid="ignore"):
                u = np.round(px[:, 0])
                v = np.round(px[:, 1])
            inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
            ui, vi = u[inside].astype(np.int64), v[inside].astype(np.int64)
            ok = np.zeros(len(d), bool)
            ok[inside] = valid[s, vi, ui]
            idx = np.nonzero(ok)[0]
            ui, vi = u[idx].astype(np.int64), v[idx].astype(np.int64)
            ds = depths[s, vi, ui].astype(np.float64)
            rays_s = geometry.pixel_rays(K[s], ui, vi)
            Xs = (rays_s * ds[:, None]) @ cam_to_world[s, :3, :3].T + cam_to_world[s, :3, 3]
            back, zb = geometry.project(K[r], world_to_cam[r], Xs)
            err_px = np.hypot(back[:, 0] - cols[idx], back[:, 1] - rows[idx])
            agree = (err_px < params.px) & (np.abs(zb - d[idx]) < params.rel_depth * d[idx])
            good = idx[agree]
            acc[good] += Xs[agree]
            col_acc[good] += images[s, vi[agree], ui[agree]]
            count[good] += 1
        keep = count >= params.min_views
        vmask = np.zeros((H, W), bool)
        vmask[rows[keep], cols[keep]] = True
        cmap = np.zeros((H, W), np.int64)
        cmap[rows, cols] = count
        n = (count[keep] + 1)[:, None]
        out.append(ViewPoints(vmask, cmap, acc[keep] / n, (col_acc[keep] / n).astype(np.float32),
                              np.stack([rows[keep], cols[keep]], 1)))
    return out


def estimate_normals(points: np.ndarray, toward: np.ndarray, knn: int = 20) -> np.ndarray:
    """Unit normals from a local plane fit (Open3D, ``knn`` neighbours), flipped so that
    ``n . toward >= 0`` (``toward``: per-point direction to a camera that saw it)."""
    import open3d as o3d

    if len(points) < 3:
        n = toward / np.maximum(np.linalg.norm(toward, axis=1, keepdims=True), 1e-12)
        return n.astype(np.float32)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(knn, len(points) - 1)))
    n = np.asarray(pc.normals)
    flip = np.einsum("ij,ij->i", n, toward) < 0
    n[flip] *= -1
    return n.astype(np.float32)


def fuse_views(views: list[ViewPoints], point_conf: list[np.ndarray], world_to_cam: np.ndarray,
               voxel_mm: float, normal_knn: int = 20) -> PointCloud:
    """Merge per-view consistent points into one cloud: voxel averaging, then normals.

    ``point_conf[i]`` is the confidence of ``views[i]``'s points, in [0, 1].
    """
    centres = np.stack([geometry.camera_center(T) for T in world_to_cam])
    pts, cols, conf, dirs = [], [], [], []
    for i, (vp, c) in enumerate(zip(views, point_conf)):
        pts.append(vp.points_mm)
        cols.append(vp.colors)
        conf.append(c)
        d = centres[i] - vp.points_mm
        dirs.append(d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12))
    P, Ccol, Cf, Dv = (np.concatenate(a) for a in (pts, cols, conf, dirs))
    if voxel_mm > 0:
        P, Ccol, Cf, Dv = voxel_downsample(P, voxel_mm, Ccol, Cf, Dv)
    normals = estimate_normals(P, Dv, normal_knn)
    return PointCloud(points_mm=P.astype(np.float64), colors=np.clip(Ccol, 0, 1).astype(np.float32),
                      normals=normals, confidence=np.clip(Cf, 0, 1).astype(np.float32))
