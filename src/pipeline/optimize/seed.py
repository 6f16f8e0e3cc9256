"""Surfels seeded from an init cloud (normalised frame): the trainer's starting parameters
(:func:`init_params`; the model and its files are :mod:`pipeline.surfels`)."""
from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial import cKDTree

from pipeline.geometry import rotmat_to_quat
from pipeline.rasterizer.project import SH_C0
from pipeline.surfels import SurfelInitError, SurfelParams


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] -> the SH DC coefficient whose evaluation gives that colour."""
    return (np.asarray(rgb, np.float64) - 0.5) / SH_C0


def frames_from_normals(normals: np.ndarray) -> np.ndarray:
    """``(N, 3)`` unit normals -> ``(N, 3, 3)`` rotations whose third column is the normal
    (tangent axes: any orthonormal pair; a surfel is isotropic at init)."""
    n = np.asarray(normals, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    # Helper axis least aligned with n, so the cross product never degenerates.
    helper = np.zeros_like(n)
    helper[np.arange(len(n)), np.argmin(np.abs(n), axis=1)] = 1.0
    tu = np.cross(helper, n)
    tu /= np.linalg.norm(tu, axis=1, keepdims=True)
    tv = np.cross(n, tu)
    return np.stack([tu, tv, n], axis=2)


def random_quats(n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniformly random unit quaternions (2DGS draws random rotations)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def knn_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """2DGS's initial scale: ``sqrt(mean squared distance to the k nearest neighbours)``.

    Coincident points would give 0; the floor is a thousandth of the cloud's median
    spacing (or 1e-7 for a single point), so every log-scale is finite."""
    n = len(points)
    if n == 1:
        return np.full(1, 1e-2)
    kk = min(k, n - 1)
    d, _ = cKDTree(points).query(points, k=kk + 1)
    d = d[:, 1:]
    s = np.sqrt(np.mean(d * d, axis=1))
    floor = max(float(np.median(s)) * 1e-3, 1e-7)
    return np.maximum(s, floor)


def init_params(points_norm: np.ndarray, normals: np.ndarray | None, colors: np.ndarray, sh_degree: int,
                opacity: float, rng: np.random.Generator, dtype=torch.float32, where: str = "init cloud") -> SurfelParams:
    """Surfels seeded from a cloud (normalised frame): centres at the points, normal from
    the point normal (random rotation when ``normals`` is None, as 2DGS), both log-scales
    from :func:`knn_scales`, colour as SH DC (higher bands 0), opacity ``opacity``."""
    points_norm = np.asarray(points_norm, np.float64)
    n = len(points_norm)
    if n == 0:
        raise SurfelInitError(f"{where}: no point to seed surfels from (an init stage that matched nothing?)")
    if not np.all(np.isfinite(points_norm)):
        raise SurfelInitError(f"{where}: non-finite point coordinates")
    if not 0 < opacity < 1:
        raise ValueError(f"initial opacity must be in (0, 1), got {opacity}")
    quats = random_quats(n, rng) if normals is None else rotmat_to_quat(frames_from_normals(normals))
    log_s = np.log(knn_scales(points_norm))
    k = (sh_degree + 1) ** 2

    def leaf(a) -> torch.Tensor:
        return torch.tensor(np.asarray(a), dtype=dtype).requires_grad_(True)

    return SurfelParams(
        means=leaf(points_norm),
        log_scales=leaf(np.repeat(log_s[:, None], 2, axis=1)),
        quats=leaf(quats),
        opacity_logits=leaf(np.full(n, math.log(opacity / (1 - opacity)))),
        sh_dc=leaf(rgb_to_sh_dc(colors)[:, None, :]),
        sh_rest=leaf(np.zeros((n, k - 1, 3))),
    )
