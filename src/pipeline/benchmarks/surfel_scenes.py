"""Realistic benchmark scenes: surfels tiling an object's surface, seen by a DTU camera.

The object is a bumpy sphere of radius ~0.55 in scan24's normalised frame (mapped to
world millimetres by its ``scale_mat``), so it fills the view like the DTU objects do.
Surfels lie tangent to the surface with Fibonacci-spaced centres and scales of
0.35-0.9 times the centre spacing (overlapping, as after 2DGS training); opacities are
uniform in [0.5, 1], colours uniform in [0, 1].
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from pipeline import geometry
from pipeline.geometry import rotmat_to_quat
from pipeline.rasterizer.types import Camera, Surfels

BUNDLED_SCAN = Path(__file__).resolve().parents[3] / "data" / "raw" / "dtu" / "scan24"
VIEW = 23
_RADIUS = 0.55
_BUMP = 0.08


def _radius(d: torch.Tensor) -> torch.Tensor:
    """Surface radius along unit directions ``d`` (N, 3)."""
    return _RADIUS * (1 + _BUMP * (torch.sin(3 * d[:, 0]) * torch.cos(2 * d[:, 1]) + 0.5 * torch.sin(4 * d[:, 2])))


def dtu_camera(width: int, height: int, scan: Path = BUNDLED_SCAN, view: int = VIEW) -> tuple[Camera, np.ndarray]:
    """Camera ``view`` of the bundled scan resized to ``width x height``; also returns
    the scan's ``norm_to_world`` (4x4)."""
    from pipeline.data.dtu import load_cameras

    cams = load_cameras(scan)
    src_w, src_h = 800, 600  # the bundled images' size, which the cameras refer to
    K = geometry.scale_intrinsics(cams.K[view], width / src_w, height / src_h)
    scale = float(cams.norm_to_world[0, 0])
    center = geometry.camera_center(cams.world_to_cam[view])
    dist = float(np.linalg.norm(center - cams.norm_to_world[:3, 3]))
    # near/far bracket the unit sphere around the object (world mm).
    cam = Camera(K=K, world_to_cam=cams.world_to_cam[view], width=width, height=height,
                 near=max(dist - 2 * scale, 1.0), far=dist + 2 * scale)  # fmt: skip
    return cam, cams.norm_to_world


def object_surfels(num: int, norm_to_world: np.ndarray, seed: int = 0, dtype=torch.float32) -> Surfels:
    """``num`` surfels tiling the bumpy sphere, in world millimetres."""
    g = torch.Generator().manual_seed(seed)
    i = torch.arange(num, dtype=torch.float64) + 0.5
    phi = torch.arccos(1 - 2 * i / num)
    theta = math.pi * (1 + math.sqrt(5)) * i
    d = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], 1)
    x = (d * _radius(d)[:, None]).requires_grad_(True)
    # Normal = gradient of |x| - r(x / |x|).
    f = x.norm(dim=1) - _radius(x / x.norm(dim=1, keepdim=True))
    (n,) = torch.autograd.grad(f.sum(), x)
    x = x.detach()
    n = n / n.norm(dim=1, keepdim=True)
    helper = torch.where((n[:, 2:3].abs() < 0.9), torch.tensor([0.0, 0, 1], dtype=n.dtype), torch.tensor([1.0, 0, 0], dtype=n.dtype))
    t_u = torch.linalg.cross(helper.expand_as(n), n)
    t_u = t_u / t_u.norm(dim=1, keepdim=True)
    t_v = torch.linalg.cross(n, t_u)
    # A random in-plane rotation, then map the frame to the world.
    ang = torch.rand(num, generator=g, dtype=torch.float64) * 2 * math.pi
    c, s = torch.cos(ang)[:, None], torch.sin(ang)[:, None]
    t_u, t_v = c * t_u + s * t_v, -s * t_u + c * t_v
    S = torch.from_numpy(norm_to_world)
    scale = float(S[0, 0])
    R_norm = torch.stack([t_u, t_v, n], dim=2)  # norm_to_world is a similarity: same rotation part
    R_world = (S[:3, :3] / scale) @ R_norm
    means = x @ S[:3, :3].T + S[:3, 3]
    spacing = math.sqrt(4 * math.pi * _RADIUS**2 / num) * scale
    scales = spacing * (0.35 + 0.55 * torch.rand(num, 2, generator=g, dtype=torch.float64))
    return Surfels(
        means=means.to(dtype),
        quats=torch.from_numpy(rotmat_to_quat(R_world.numpy())).to(dtype),
        scales=scales.to(dtype),
        opacities=(0.5 + 0.5 * torch.rand(num, generator=g, dtype=torch.float64)).to(dtype),
        features=torch.rand(num, 3, generator=g, dtype=torch.float64).to(dtype),
    )
