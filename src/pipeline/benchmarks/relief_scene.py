"""A small textured relief scene built on real cameras, rendered exactly by ray casting,
for checking the priors and the GCF loss against ground truth.

Frames and units: world mm, OpenCV camera axes, integer pixel centres
(``pipeline.geometry``).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.raycast import MeshCaster


def relief_mesh(center: np.ndarray, normal: np.ndarray, size_mm: float, amplitude_mm: float,
                resolution: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A square height-field plate (Gaussian bumps) centred at ``center`` facing ``normal``.

    Returns ``(vertices (N, 3) world mm, triangles (M, 3) int)``.
    """
    rng = np.random.default_rng(seed)
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    u, v = np.meshgrid(np.linspace(-0.5, 0.5, resolution), np.linspace(-0.5, 0.5, resolution))
    h = np.zeros_like(u)
    for _ in range(12):
        cu, cv = rng.uniform(-0.4, 0.4, 2)
        s = rng.uniform(0.05, 0.15)
        h += rng.uniform(-1, 1) * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * s * s))
    h *= amplitude_mm / max(np.abs(h).max(), 1e-9)
    verts = center + size_mm * (u[..., None] * a + v[..., None] * b) + h[..., None] * n
    idx = np.arange(resolution * resolution).reshape(resolution, resolution)
    q = np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], -1).reshape(-1, 4)
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    return verts.reshape(-1, 3), tris


def albedo(points_world: np.ndarray, seed: int) -> np.ndarray:
    """A band-limited random texture of the 3D position (wavelengths 6-40 mm), in [0.1, 0.9]."""
    rng = np.random.default_rng(seed)
    k = 48
    dirs = rng.normal(size=(k, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    omega = dirs * (2 * np.pi / rng.uniform(6.0, 40.0, size=(k, 1)))
    phase = rng.uniform(0, 2 * np.pi, k)
    s = np.sin(points_world @ omega.T + phase).sum(-1) / np.sqrt(k / 2)
    return 0.5 + 0.4 * np.tanh(s)


@dataclass
class TexturedScene:
    """Rendered views of a textured relief plate with ground-truth depth and normals."""

    images: np.ndarray  # (N, H, W, 3) float32 in [0, 1]
    K: np.ndarray  # (N, 3, 3)
    world_to_cam: np.ndarray  # (N, 4, 4)
    depth_mm: np.ndarray  # (N, H, W) camera z at pixel centres, 0 where empty
    normal_cam: np.ndarray  # (N, H, W, 3) GT face normals, camera frame, facing the camera
    vertices: np.ndarray
    triangles: np.ndarray


def textured_relief_scene(K: np.ndarray, world_to_cam: np.ndarray, width: int, height: int,
                          center: np.ndarray, size_mm: float = 300.0, amplitude_mm: float = 15.0,
                          seed: int = 0, supersample: int = 2,
                          gains: tuple[float, ...] = (1.0, 0.8, 1.15), offsets: tuple[float, ...] = (0.0, 0.05, -0.04)
                          ) -> TexturedScene:
    """Render a textured, Lambert-shaded relief plate into the given cameras.

    The plate faces the mean viewing direction. Each view gets its own exposure (gain,
    offset) so that features must be robust to a global lighting change. Colours are the
    mean of ``supersample^2`` rays per pixel (anti-aliasing); depth and normals are at
    the pixel centre.
    """
    view_dirs = np.stack([T[2, :3] for T in world_to_cam])  # camera z axes in the world
    facing = -view_dirs.mean(0)
    verts, tris = relief_mesh(center, facing, size_mm, amplitude_mm, 151, seed)
    light = facing + np.array([0.3, -0.4, 0.2])
    light /= np.linalg.norm(light)
    tint = np.array([1.0, 0.9, 0.75])
    caster = MeshCaster(verts, tris)
    images, depths, normals = [], [], []
    for v, (k, T) in enumerate(zip(K, world_to_cam)):
        acc = np.zeros((height, width, 3))
        for sy in range(supersample):
            for sx in range(supersample):
                off = ((sx + 0.5) / supersample - 0.5, (sy + 0.5) / supersample - 0.5)
                hits = caster.cast(k, T, height, width, off)
                hit = hits.depth_mm > 0
                n_world = hits.normal_cam @ T[:3, :3]
                shade = 0.35 + 0.65 * np.abs(n_world @ light)
                a = albedo(np.nan_to_num(hits.points_world), seed + 1)
                grey = np.where(hit, a * shade, 0.08)
                acc += grey[..., None] * tint
        img = acc / supersample**2 * gains[v % len(gains)] + offsets[v % len(offsets)]
        centre = caster.cast(k, T, height, width)
        images.append(np.clip(img, 0, 1).astype(np.float32))
        depths.append(centre.depth_mm)
        normals.append(centre.normal_cam)
    return TexturedScene(np.stack(images), np.asarray(K), np.asarray(world_to_cam), np.stack(depths),
                         np.stack(normals), verts, tris)
