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


# Largest cell of the primitives (mm): fine enough that culling hidden triangles from the
# ground truth (scenes.visible_gt_mesh) leaves at most this much of hidden surface.
CELL_MM = 2.0


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


def _grid_triangles(nu: int, nv: int, offset: int = 0) -> np.ndarray:
    """Triangles of a ``(nv + 1) x (nu + 1)`` row-major vertex grid, counter-clockwise when
    u runs right and v up."""
    i, j = np.meshgrid(np.arange(nu), np.arange(nv))
    a = (j * (nu + 1) + i).ravel() + offset
    b, c, d = a + 1, a + nu + 2, a + nu + 1
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def merge(pieces: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """One mesh from several ``(vertices, triangles)``."""
    verts, tris, n = [], [], 0
    for v, f in pieces:
        verts.append(v)
        tris.append(f + n)
        n += len(v)
    return np.concatenate(verts), np.concatenate(tris)


def rectangle(origin, eu, ev, cell_mm: float = CELL_MM) -> tuple[np.ndarray, np.ndarray]:
    """Planar grid over ``origin + s eu + t ev`` (s, t in [0, 1]), cells <= ``cell_mm``;
    its normal is ``eu x ev``."""
    origin, eu, ev = (np.asarray(a, np.float64) for a in (origin, eu, ev))
    nu = max(1, int(np.ceil(np.linalg.norm(eu) / cell_mm)))
    nv = max(1, int(np.ceil(np.linalg.norm(ev) / cell_mm)))
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1))
    v = origin + s.reshape(-1, 1) * eu + t.reshape(-1, 1) * ev
    return v, _grid_triangles(nu, nv)


def box(size: tuple[float, float, float], corner: tuple[float, float, float],
        cell_mm: float = CELL_MM) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box with sharp edges (each face its own grid), min corner at
    ``corner``, normals outwards."""
    (sx, sy, sz), c = size, np.asarray(corner, np.float64)
    X, Y, Z = np.array([sx, 0, 0.0]), np.array([0, sy, 0.0]), np.array([0, 0, sz])
    faces = [(c, Y, X), (c + Z, X, Y), (c, X, Z), (c + Y, Z, X), (c, Z, Y), (c + X, Y, Z)]
    return merge([rectangle(o, eu, ev, cell_mm) for o, eu, ev in faces])


def _polar_cap(radius: float, z: float, segments: int, cell_mm: float, up: bool) -> tuple[np.ndarray, np.ndarray]:
    """Disk of ``radius`` at height ``z``: centre plus rings <= ``cell_mm`` apart."""
    rings = max(1, int(np.ceil(radius / cell_mm)))
    ang = 2 * np.pi * np.arange(segments) / segments
    r = radius * np.arange(1, rings + 1) / rings
    ring_v = np.stack([np.outer(r, np.cos(ang)), np.outer(r, np.sin(ang)), np.full((rings, segments), z)], -1)
    v = np.concatenate([[[0.0, 0.0, z]], ring_v.reshape(-1, 3)])
    k = np.arange(segments)
    k1 = (k + 1) % segments
    fan = np.stack([np.zeros(segments, np.int64), 1 + k, 1 + k1], 1)
    j = np.arange(rings - 1)[:, None] * segments
    a, b, c, d = (1 + j + k).ravel(), (1 + j + k1).ravel(), (1 + j + segments + k1).ravel(), (1 + j + segments + k).ravel()
    f = np.concatenate([fan, np.stack([a, d, c], 1), np.stack([a, c, b], 1)])  # counter-clockwise from above
    return v, (f if up else f[:, ::-1])


def cylinder(radius: float, height: float, base_xy: tuple[float, float],
             cell_mm: float = CELL_MM) -> tuple[np.ndarray, np.ndarray]:
    """Vertical closed cylinder standing on z = 0, normals outwards. Wall and caps have
    their own vertices, so smooth shading keeps the rim sharp."""
    segments = max(48, int(np.ceil(2 * np.pi * radius / cell_mm)))
    rows = max(1, int(np.ceil(height / cell_mm)))
    ang = 2 * np.pi * np.arange(segments + 1) / segments  # the seam column repeats
    zs = np.linspace(0.0, height, rows + 1)
    wall = np.stack([np.broadcast_to(radius * np.cos(ang), (rows + 1, segments + 1)),
                     np.broadcast_to(radius * np.sin(ang), (rows + 1, segments + 1)),
                     np.broadcast_to(zs[:, None], (rows + 1, segments + 1))], -1).reshape(-1, 3)
    v, f = merge([(wall, _grid_triangles(segments, rows)),
                   _polar_cap(radius, height, segments, cell_mm, up=True),
                   _polar_cap(radius, 0.0, segments, cell_mm, up=False)])
    v[:, :2] += np.asarray(base_xy)
    return v, f


def ground_disk(radius: float, cell_mm: float = CELL_MM) -> tuple[np.ndarray, np.ndarray]:
    """The table around an object, as a disk at z = 0 facing up."""
    return _polar_cap(radius, 0.0, max(48, int(np.ceil(2 * np.pi * radius / cell_mm))), cell_mm, up=True)


def textureless_blob(seed: int) -> list[Part]:
    """A large smooth ellipsoid dome in one plain colour (the textureless region) on a
    textured plinth ring."""
    rng = np.random.default_rng(seed)
    v, f = icosphere(6)  # 81920 faces
    a, b, c = 110.0 + rng.uniform(-8, 8), 90.0 + rng.uniform(-8, 8), 80.0
    v = v * [a, b, c] + [0.0, 0.0, 65.0]
    v, f = drop_below_ground(v, f)
    ring_v, ring_f = cylinder(radius=a + 8.0, height=16.0, base_xy=(0.0, 0.0))
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
