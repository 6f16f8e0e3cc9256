"""Ray casting against a triangle mesh (Open3D ``RaycastingScene``): per-pixel depth and
normals seen by a camera, and point-to-surface distances.

Frames and units: world mm, OpenCV camera axes, integer pixel centres
(:mod:`pipeline.geometry`). Rays have camera-frame z = 1, so a hit's ray parameter is its
camera depth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline import geometry


@dataclass
class RayHits:
    """Per-pixel ray casting result for one camera."""

    depth_mm: np.ndarray  # (H, W) camera-frame z; 0 where the ray misses (no depth, see init.io.DepthMap)
    normal_cam: np.ndarray  # (H, W, 3) unit face normals in the camera frame, facing the camera; 0 on misses
    points_world: np.ndarray  # (H, W, 3) hit points, world mm; nan on misses


class MeshCaster:
    """Ray casting against one triangle mesh (world mm); the BVH is built once."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                                 o3d.core.Tensor(np.asarray(triangles, np.uint32)))

    def cast(self, K: np.ndarray, world_to_cam: np.ndarray, height: int, width: int,
             subpixel: tuple[float, float] = (0.0, 0.0)) -> RayHits:
        """Cast one ray per pixel centre (shifted by ``subpixel`` = (dx, dy) pixels)."""
        ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
        rays_cam = geometry.pixel_rays(K, xs + subpixel[0], ys + subpixel[1])
        R = world_to_cam[:3, :3]
        origin = geometry.camera_center(world_to_cam)
        dirs_world = rays_cam @ R  # R^T d for row vectors; |d| kept so t_hit is camera z
        rays = np.concatenate([np.broadcast_to(origin, dirs_world.shape), dirs_world], -1).astype(np.float32)
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)  # in units of |d|, i.e. camera z
        hit = np.isfinite(t)
        n_cam = ans["primitive_normals"].numpy().astype(np.float64) @ R.T
        # Face the camera: n . ray < 0 (the 2DGS renderer orients surfel normals this way).
        n_cam[np.sum(n_cam * rays_cam, -1) > 0] *= -1
        n_cam[~hit] = 0.0
        pts = origin + dirs_world * np.where(hit, t, np.nan)[..., None]
        return RayHits(depth_mm=np.where(hit, t, 0.0), normal_cam=n_cam, points_world=pts)

    def occluded(self, rays: np.ndarray) -> np.ndarray:
        """``(N,)`` bool: whether the surface meets each ray ``(N, 6)`` = origin, direction
        (world mm) between its origin and origin + direction (Open3D ``tfar = 1``)."""
        query = self._o3d.core.Tensor(np.asarray(rays, np.float32))
        return self.scene.test_occlusions(query, tfar=1.0).numpy()

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (mm, float64 ``(N,)``) of world points ``(N, 3)`` to the surface."""
        query = self._o3d.core.Tensor(np.asarray(points, np.float32))
        return self.scene.compute_distance(query).numpy().astype(np.float64)


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unsigned distance (mm) of points ``(N, 3)`` to a triangle mesh, all world mm."""
    return MeshCaster(vertices, triangles).distance(points)
