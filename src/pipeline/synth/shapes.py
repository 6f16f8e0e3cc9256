"""Procedural objects of the synthetic suite, built in a local frame (mm, z up, origin on
the ground under the object) and placed into the DTU world frame by :mod:`.scenes`."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d


@dataclass
class Part:
    """One piece of an object. ``texture`` names an albedo function of :mod:`.texture`;
    ``smooth`` selects interpolated vertex normals for shading (else face normals, which
    keeps box edges sharp)."""

    vertices: np.ndarray  # (V, 3) local mm
    triangles: np.ndarray  # (F, 3) int
    texture: str
    smooth: bool


def _arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(mesh.vertices, np.float64).copy(), np.asarray(mesh.triangles, np.int64).copy()


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere with near-uniform triangles (edge ~ 1.1 / 2^subdivisions)."""
    mesh = o3d.geometry.TriangleMesh.create_icosahedron(radius=1.0).subdivide_midpoint(subdivisions)
    v, f = _arrays(mesh)
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def drop_below_ground(v: np.ndarray, f: np.ndarray, z_min: float = -2.0) -> tuple[np.ndarray, np.ndarray]:
    """Remove triangles lying entirely below ``z_min`` (hidden inside the ground)."""
    keep_f = f[(v[f][:, :, 2] >= z_min).any(axis=1)]
    used = np.unique(keep_f)
    remap = np.full(len(v), -1)
    remap[used] = np.arange(len(used))
    return v[used], remap[keep_f]


def box(size: tuple[float, float, float], corner: tuple[float, float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box with sharp edges: 12 triangles, min corner at ``corner``."""
    v, f = _arrays(o3d.geometry.TriangleMesh.create_box(*size))
    return v + np.asarray(corner), f


def cylinder(radius: float, height: float, base_xy: tuple[float, float], segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Vertical closed cylinder standing on z = 0."""
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius=radius, height=height, resolution=segments, split=8)
    v, f = _arrays(mesh)
    v[:, 2] += height / 2.0
    v[:, :2] += np.asarray(base_xy)
    return v, f


def textureless_blob(seed: int) -> list[Part]:
    """A large smooth ellipsoid dome in one plain colour (the textureless region) on a
    textured plinth ring."""
    rng = np.random.default_rng(seed)
    v, f = icosphere(6)  # 81920 faces
    a, b, c = 110.0 + rng.uniform(-8, 8), 90.0 + rng.uniform(-8, 8), 80.0
    v = v * [a, b, c] + [0.0, 0.0, 65.0]
    v, f = drop_below_ground(v, f)
    ring_v, ring_f = cylinder(radius=a + 8.0, height=16.0, base_xy=(0.0, 0.0), segments=96)
    ring_v[:, 1] *= (b + 8.0) / (a + 8.0)
    return [Part(v, f, "plain", True), Part(ring_v, ring_f, "noise", False)]


def relief_sphere(seed: int) -> list[Part]:
    """A sphere covered in mm-scale bumps and ridges (fine geometric detail)."""
    rng = np.random.default_rng(seed)
    v, f = icosphere(7)  # 327680 faces, edges ~0.7 mm at r = 85 mm
    r = 85.0
    waves = rng.normal(size=(6, 3))
    waves /= np.linalg.norm(waves, axis=1, keepdims=True)
    periods = rng.uniform(3.0, 8.0, size=6)  # mm on the surface
    phases = rng.uniform(0, 2 * np.pi, size=6)
    p = v * r
    disp = sum(np.sin(2 * np.pi * (p @ w) / T + ph) for w, T, ph in zip(waves, periods, phases))
    disp = 1.5 * disp / np.sqrt(len(periods))  # ~1.5 mm amplitude
    v = v * (r + disp)[:, None] + [0.0, 0.0, 70.0]
    v, f = drop_below_ground(v, f)
    return [Part(v, f, "noise", True)]


def thin_structures(seed: int) -> list[Part]:
    """A sharp-edged box carrying thin fins, and thin rods beside it, turned 35 degrees
    about the vertical so the cameras (around local +x) see box corners and the fins
    obliquely rather than face-on."""
    rng = np.random.default_rng(seed)
    parts = [Part(*box((130.0, 100.0, 55.0), (-65.0, -50.0, 0.0)), "noise", False)]
    for k, x in enumerate((-40.0, 0.0, 40.0)):
        thick = 2.0 + rng.uniform(0, 1.5)
        height = 45.0 + 12.0 * k
        parts.append(Part(*box((thick, 80.0, height), (x - thick / 2, -40.0, 55.0)), "noise", False))
    for (x, y) in ((90.0, 30.0), (90.0, -35.0), (-90.0, 0.0)):
        parts.append(Part(*cylinder(radius=2.0 + rng.uniform(0, 1.0), height=rng.uniform(90, 130), base_xy=(x, y)),
                          "noise", True))
    c, s = np.cos(np.radians(35.0)), np.sin(np.radians(35.0))
    yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return [Part(p.vertices @ yaw.T, p.triangles, p.texture, p.smooth) for p in parts]
