"""Where surfels may be, and how many a scene gets (params ``optimize.region`` and
``optimize.densify.surfels_per_object_px``; docs/optimize.md "Surfels only where the object is").

The region is the sphere of ``sphere_radius`` in the normalised frame (the unit sphere of
scale_mat, which the mesh stage cuts to as well) and, when the training uses masks (given
or derived by ``gcgs masks``), the masks' visual hull: a centre that projects, in front of
an input view's camera and inside its image, onto a pixel more than ``hull_tolerance_px``
from that view's mask is outside, since that view sees background through it. A view the
centre projects out of (or behind) says nothing. Surfels there can only explain
background, so the trainer never seeds, grows or keeps them.

The budget follows what the views show instead of a fixed count: ``surfels_per_object_px``
times the mean object area of the input views in pixels of the data resolution (mask
pixels; without masks the pixels whose ray crosses the sphere), at most ``max_surfels``.

Frames: centres in the normalised frame; ``world_to_cam`` normalised-to-camera (OpenCV
axes); ``K`` the data resolution's intrinsics with integer pixel centres.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import ndimage

from pipeline.config.optimize import OptimizeConfig


@dataclass
class SurfelRegion:
    """The sphere and, with masks, the masks' visual hull (module docstring)."""

    sphere_radius: float
    K: np.ndarray  # (V, 3, 3) intrinsics of the data resolution
    world_to_cam: np.ndarray  # (V, 4, 4) normalised frame -> camera
    hull: list[np.ndarray] | None  # per view (H, W) bool: the mask grown by the tolerance; None: no masks

    def contains(self, means: torch.Tensor | np.ndarray) -> torch.Tensor:
        """``(N,)`` bool on the centres' device: which centres ``(N, 3)`` (normalised frame)
        are inside."""
        means = torch.as_tensor(means)
        p = means.detach().to(torch.float64).cpu().numpy()
        inside = np.einsum("ij,ij->i", p, p) <= self.sphere_radius ** 2
        if self.hull is not None:
            for K, w2c, hull in zip(self.K, self.world_to_cam, self.hull):
                cam = p @ w2c[:3, :3].T + w2c[:3, 3]
                z = cam[:, 2]
                front = z > 1e-9
                uv = np.full((len(p), 2), -1.0)
                uv[front] = (cam[front, :2] / z[front, None]) @ K[:2, :2].T + K[:2, 2]
                u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
                h, w = hull.shape
                seen = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
                idx = np.flatnonzero(seen)
                inside[idx[~hull[v[idx].astype(np.int64), u[idx].astype(np.int64)]]] = False
        return torch.from_numpy(inside).to(means.device)


def region_from_views(scene, masks: list[np.ndarray] | None, cfg: OptimizeConfig) -> SurfelRegion | None:
    """The region of ``scene`` (its ``K`` and ``world_to_cam_normalised()``) with the training's
    ``masks`` (full-resolution bool per input view, None without masks); None when
    ``optimize.region.enabled`` is off."""
    rc = cfg.region
    if not rc.enabled:
        return None
    hull = None
    if masks is not None:
        r = int(math.ceil(rc.hull_tolerance_px))
        if r > 0:
            yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
            disk = xx * xx + yy * yy <= rc.hull_tolerance_px ** 2
            hull = [ndimage.binary_dilation(np.asarray(m, bool), structure=disk) for m in masks]
        else:
            hull = [np.asarray(m, bool) for m in masks]
    return SurfelRegion(rc.sphere_radius, np.asarray(scene.K, np.float64),
                        np.asarray(scene.world_to_cam_normalised(), np.float64), hull)


def sphere_silhouette(K: np.ndarray, world_to_cam: np.ndarray, shape: tuple[int, int], radius: float) -> np.ndarray:
    """``(H, W)`` bool: the pixels whose centre ray crosses the origin-centred sphere of
    ``radius`` (normalised frame) in front of the camera; every pixel when the camera is
    inside it."""
    h, w = shape
    c = world_to_cam[:3, 3]  # the sphere's centre in the camera frame
    if float(c @ c) <= radius ** 2:
        return np.ones(shape, bool)
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    along = d @ c
    return (along > 0) & (float(c @ c) - along * along <= radius ** 2)


@dataclass
class SurfelBudget:
    surfels: int
    object_px: float  # mean object pixels over the input views (data resolution)
    source: str  # masks | sphere
    per_object_px: float
    ceiling: int

    def facts(self) -> dict:
        return {"surfels": self.surfels, "object_px_mean": round(self.object_px, 1), "object_area_from": self.source,
                "surfels_per_object_px": self.per_object_px, "ceiling": self.ceiling,
                "rule": "min(ceiling, surfels_per_object_px x object_px_mean)" if self.per_object_px > 0 else "ceiling"}


def surfel_budget(scene, masks: list[np.ndarray] | None, cfg: OptimizeConfig) -> SurfelBudget:
    """The surfel budget of ``scene`` (module docstring) with the training's ``masks``."""
    per_px, ceiling = cfg.densify.surfels_per_object_px, cfg.densify.max_surfels
    if masks is not None:
        areas, source = [float(np.count_nonzero(m)) for m in masks], "masks"
    else:
        w2c = scene.world_to_cam_normalised()
        areas = [float(np.count_nonzero(sphere_silhouette(scene.K[i], w2c[i], (scene.height, scene.width),
                                                           cfg.region.sphere_radius))) for i in range(scene.num_views)]
        source = "sphere"
    object_px = float(np.mean(areas))
    surfels = ceiling if per_px <= 0 else max(1, min(ceiling, int(math.ceil(per_px * object_px))))
    return SurfelBudget(surfels, object_px, source, per_px, ceiling)
