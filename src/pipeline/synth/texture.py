"""Solid (3D) procedural textures: albedo as a function of the surface point, so every
view sees the same colour at the same point. Deterministic from the seed."""
from __future__ import annotations

import numba
import numpy as np

@numba.njit(cache=True, inline="always")
def _hash(ix: int, iy: int, iz: int, seed: int) -> float:
    """Uniform [0, 1) per integer lattice point (splitmix64 finaliser)."""
    h = (np.uint64(ix) * np.uint64(0x9E3779B97F4A7C15)) ^ (np.uint64(iy) * np.uint64(0xC2B2AE3D27D4EB4F))
    h ^= (np.uint64(iz) * np.uint64(0x165667B19E3779F9)) ^ (np.uint64(seed) * np.uint64(0x27D4EB2F165667C5))
    h ^= h >> np.uint64(31)
    h *= np.uint64(0xBF58476D1CE4E5B9)
    h ^= h >> np.uint64(27)
    h *= np.uint64(0x94D049BB133111EB)
    h ^= h >> np.uint64(33)
    return float(h >> np.uint64(11)) / 9007199254740992.0


@numba.njit(cache=True, parallel=True)
def _value_noise(points: np.ndarray, cell_mm: float, seed: int) -> np.ndarray:
    out = np.empty(points.shape[0])
    for n in numba.prange(points.shape[0]):
        q0, q1, q2 = points[n, 0] / cell_mm, points[n, 1] / cell_mm, points[n, 2] / cell_mm
        i0, i1, i2 = np.floor(q0), np.floor(q1), np.floor(q2)
        f0, f1, f2 = q0 - i0, q1 - i1, q2 - i2
        u0, u1, u2 = f0 * f0 * (3 - 2 * f0), f1 * f1 * (3 - 2 * f1), f2 * f2 * (3 - 2 * f2)
        acc = 0.0
        for dx in range(2):
            wx = u0 if dx else 1 - u0
            for dy in range(2):
                wy = u1 if dy else 1 - u1
                for dz in range(2):
                    wz = u2 if dz else 1 - u2
                    acc += wx * wy * wz * _hash(int(i0) + dx, int(i1) + dy, int(i2) + dz, seed)
        out[n] = acc
    return out


def value_noise(points: np.ndarray, cell_mm: float, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] with lattice spacing ``cell_mm`` (points in mm)."""
    return _value_noise(np.ascontiguousarray(points, dtype=np.float64), float(cell_mm), int(seed))


def fbm(points: np.ndarray, cell_mm: float, seed: int, octaves: int = 3) -> np.ndarray:
    total, amp, norm = np.zeros(len(points)), 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(points, cell_mm / 2**o, seed + 101 * o)
        norm += amp
        amp *= 0.5
    return total / norm


def palette(seed: int) -> np.ndarray:
    """Three RGB colours, deterministic from the seed."""
    rng = np.random.default_rng(seed + 7)
    return rng.uniform(0.15, 0.9, size=(3, 3))


def albedo(kind: str, points_local: np.ndarray, seed: int) -> np.ndarray:
    """RGB albedo in [0, 1] of points (local object frame, mm) for a texture ``kind``."""
    n = len(points_local)
    if n == 0:
        return np.zeros((0, 3))
    if kind == "plain":
        return np.tile([0.72, 0.62, 0.52], (n, 1))
    if kind == "noise":
        cols = palette(seed)
        a = fbm(points_local, 6.0, seed)
        b = value_noise(points_local, 2.0, seed + 1)
        mix = np.clip(1.6 * (a - 0.5) + 0.5, 0, 1)[:, None]
        base = mix * cols[0] + (1 - mix) * cols[1]
        speck = (b > 0.7)[:, None]
        return np.where(speck, 0.6 * base + 0.4 * cols[2], base)
    if kind == "ground":
        # DTU's table: grey with printed pattern. Checker of 20 mm plus fine noise.
        cx = np.floor(points_local[:, 0] / 20.0).astype(np.int64)
        cy = np.floor(points_local[:, 1] / 20.0).astype(np.int64)
        check = ((cx + cy) & 1).astype(np.float64)
        g = 0.35 + 0.15 * check + 0.2 * (fbm(points_local, 4.0, seed + 3, octaves=2) - 0.5)
        return np.stack([g, g * 0.97, g * 0.93], axis=1)
    raise ValueError(f"unknown texture {kind!r}")
