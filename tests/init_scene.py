"""A small analytic test scene for the init/TSDF tests: two textured spheres seen by the
bundled scan24 cameras (views 23, 24, 33), ray-cast exactly, with GT depth per view.

The texture is a sum of 3D sinusoids of the surface point (so it is the same in every
view) times Lambertian shading from a fixed light, wavelengths >= 4 pixels at the
chosen resolution. Units: world mm.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import geometry
from pipeline.data.dtu import load_scene
from pipeline.data.scene import Scene

REPO = Path(__file__).resolve().parents[1]
SCAN = REPO / "data" / "raw" / "dtu" / "scan24"


def spheres_world(scene: Scene) -> list[tuple[np.ndarray, float]]:
    """(centre mm, radius mm) of the two spheres, placed relative to the unit sphere."""
    c, r = scene.norm_to_world[:3, 3], scene.norm_scale_mm
    return [(c + np.array([0.0, 0.0, 0.0]), 0.35 * r), (c + np.array([0.35, 0.4, 0.3]) * r, 0.15 * r)]


def ray_cast(K, w2c, H, W, spheres) -> tuple[np.ndarray, np.ndarray]:
    """GT camera z (mm; 0 where no hit) and world hit points (H, W, 3)."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    rays_cam = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T  # unit z
    R, t = w2c[:3, :3], w2c[:3, 3]
    best = np.full((H, W), np.inf)
    for centre, radius in spheres:
        c = R @ centre + t
        a = (rays_cam**2).sum(-1)
        b = rays_cam @ c
        disc = b * b - a * (c @ c - radius**2)
        with np.errstate(invalid="ignore"):
            z = (b - np.sqrt(disc)) / a
        z = np.where((disc > 0) & (z > 0), z, np.inf)
        best = np.minimum(best, z)
    best = np.where(np.isfinite(best), best, 0.0)
    cam = rays_cam * best[..., None]
    world = (cam - t) @ R  # R^T (cam - t)
    return best, world


def texture(world: np.ndarray, wavelength_mm: float, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = np.zeros(world.shape[:-1])
    for i in range(12):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        lam = wavelength_mm * (1.0 + 3.0 * rng.random())
        out += np.sin(2 * np.pi * (world @ d) / lam + rng.uniform(0, 2 * np.pi))
    return 0.5 + 0.5 * np.tanh(out / 2.0)


def make_scene(width: int = 200, height: int = 150, seed: int = 0,
               spheres: list[tuple[np.ndarray, float]] | None = None,
               plain: bool = False) -> tuple[Scene, np.ndarray]:
    """The test scene at ``width x height`` and its GT depth maps ``(N, H, W)`` (0 = miss).
    ``spheres``: (centre mm, radius mm) of each part (default :func:`spheres_world`).
    ``plain``: one albedo everywhere and a light from beside the cameras, so the only
    pattern is the shading, and it covers what the cameras see."""
    base = load_scene(SCAN, resolution=(width, height))
    spheres = spheres_world(base) if spheres is None else spheres
    px_mm = 680.0 / base.K[0, 0, 0]  # pixel footprint at the object distance
    light = np.array([0.3, -0.5, -0.8])
    if plain:  # from the cameras' side and off their axis: shading over the whole visible part
        to_cams = np.mean([geometry.camera_center(T) for T in base.world_to_cam], 0) - base.norm_to_world[:3, 3]
        to_cams /= np.linalg.norm(to_cams)
        side = np.cross(to_cams, [0.0, 0.0, 1.0])
        light = -(to_cams + 0.7 * side / np.linalg.norm(side))
    light /= np.linalg.norm(light)
    images, masks, depths = [], [], []
    for K, w2c in zip(base.K, base.world_to_cam):
        z, world = ray_cast(K, w2c, height, width, spheres)
        hit = z > 0
        # Normals of whichever sphere was hit (the nearest one).
        normal = np.zeros_like(world)
        for centre, radius in spheres:
            on = hit & (np.abs(np.linalg.norm(world - centre, axis=-1) - radius) < 1e-6 * radius + 1e-6)
            normal[on] = (world[on] - centre) / radius
        shade = 0.35 + 0.65 * np.clip(-(normal @ light), 0.0, 1.0)
        albedo = 0.6 if plain else texture(world, wavelength_mm=4.0 * px_mm, seed=seed)
        grey = np.where(hit, 0.15 + 0.8 * albedo * shade, 0.05)
        rgb = np.stack([grey, 0.9 * grey + 0.05, 0.8 * grey + 0.1], -1)
        images.append(np.clip(rgb, 0, 1).astype(np.float32))
        masks.append(hit)
        depths.append(z)
    scene = Scene(
        name="test_spheres", images=np.stack(images), masks=np.stack(masks), K=base.K.copy(),
        world_to_cam=base.world_to_cam.copy(), norm_to_world=base.norm_to_world.copy(),
        view_ids=list(base.view_ids),
    )
    return scene, np.stack(depths)


def distance_to_spheres(points: np.ndarray, scene: Scene,
                        spheres: list[tuple[np.ndarray, float]] | None = None) -> np.ndarray:
    """Unsigned distance (mm) of world points to the union of the sphere surfaces."""
    d = np.full(len(points), np.inf)
    for centre, radius in spheres_world(scene) if spheres is None else spheres:
        d = np.minimum(d, np.abs(np.linalg.norm(points - centre, axis=1) - radius))
    return d


__all__ = ["make_scene", "distance_to_spheres", "ray_cast", "spheres_world", "geometry"]
