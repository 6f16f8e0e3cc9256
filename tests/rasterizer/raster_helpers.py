"""Random test scenes and a helper that renders and back-propagates random cotangents."""
from __future__ import annotations

import math

import numpy as np
import torch

from pipeline.rasterizer import Camera, RenderOutput, Surfels, rasterize

MAPS = ("features", "alpha", "depth_expected", "depth_median", "normal_cam", "normal_world", "distortion")
PARAMS = ("means", "quats", "scales", "opacities", "features")


def random_camera(width: int, height: int, seed: int = 0, near: float = 0.5, far: float = 20.0) -> Camera:
    """A camera at a random pose looking at the origin region, with a small skew."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ang = 0.3 * rng.uniform()
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    R = np.eye(3) + math.sin(ang) * Kx + (1 - math.cos(ang)) * Kx @ Kx
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = rng.normal(scale=0.1, size=3)
    f = 1.1 * width
    K = np.array([[f, 0.01 * f, width / 2 - 0.3], [0, 1.05 * f, height / 2 + 0.2], [0, 0, 1]])
    return Camera(K=K, world_to_cam=w2c, width=width, height=height, near=near, far=far)


def random_surfels(
    P: int, camera: Camera, C: int = 3, seed: int = 0, dtype=torch.float64, sh_degree: int | None = None,
    scale: tuple[float, float] = (0.03, 0.25), opacity: tuple[float, float] = (0.05, 0.95),
) -> Surfels:  # fmt: skip
    """``P`` surfels in front of ``camera`` at depths 2-6, mostly inside its view."""
    g = torch.Generator().manual_seed(seed)
    z = 2 + 4 * torch.rand(P, generator=g, dtype=torch.float64)
    xy = (torch.rand(P, 2, generator=g, dtype=torch.float64) - 0.5) * 1.1 * z[:, None] * torch.tensor(
        [camera.width / camera.K[0, 0].item(), camera.height / camera.K[1, 1].item()], dtype=torch.float64
    )
    p_cam = torch.cat([xy, z[:, None]], 1)
    R, t = camera.world_to_cam[:3, :3], camera.world_to_cam[:3, 3]
    means = (p_cam - t) @ R  # R^T (p - t), as rows
    lo, hi = scale
    olo, ohi = opacity
    if sh_degree is None:
        feats = torch.rand(P, C, generator=g, dtype=torch.float64)
    else:
        feats = 0.5 * torch.randn(P, (sh_degree + 1) ** 2, 3, generator=g, dtype=torch.float64)
    return Surfels(
        means=means.to(dtype),
        quats=torch.randn(P, 4, generator=g, dtype=torch.float64).to(dtype),
        scales=(lo + (hi - lo) * torch.rand(P, 2, generator=g, dtype=torch.float64)).to(dtype),
        opacities=(olo + (ohi - olo) * torch.rand(P, generator=g, dtype=torch.float64)).to(dtype),
        features=feats.to(dtype),
        sh_degree=sh_degree,
    )


def with_grad(s: Surfels) -> Surfels:
    """A copy whose tensors are fresh leaves requiring grad."""
    return Surfels(*(getattr(s, k).detach().clone().requires_grad_(True) for k in PARAMS), sh_degree=s.sh_degree)


def render_and_grads(
    s: Surfels, camera: Camera, backend: str, cotangent_seed: int = 1, **kw
) -> tuple[RenderOutput, dict[str, torch.Tensor]]:
    """Render, contract all maps with random cotangents, back-propagate. Returns the
    output and the gradients of every surfel parameter and of ``means2d``."""
    s = with_grad(s)
    out = rasterize(s, camera, backend, **kw)
    g = torch.Generator().manual_seed(cotangent_seed)
    loss = sum((getattr(out, k) * torch.randn(getattr(out, k).shape, generator=g, dtype=out.alpha.dtype)).sum() for k in MAPS)
    loss.backward()
    grads = {k: getattr(s, k).grad for k in PARAMS}
    grads["means2d"] = out.means2d.grad
    return out, grads
