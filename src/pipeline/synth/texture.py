"""Solid (3D) procedural textures: albedo as a function of the surface point (local frame,
mm), so every view sees the same colour at the same point. Deterministic from the seed.

Scalar numba functions, called per ray sample by the shading kernel of
:mod:`pipeline.synth.render`. The patterns are band-limited (smooth noise, soft-edged
specks and checkers, edges ~1 mm wide) so one sample per pixel does not alias at DTU
resolutions.
"""
from __future__ import annotations

import numba
import numpy as np

# Texture kinds (ids used by the kernel).
PLAIN, NOISE, GROUND = 0, 1, 2
KINDS = {"plain": PLAIN, "noise": NOISE, "ground": GROUND}
PLAIN_RGB = (0.72, 0.62, 0.52)


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


@numba.njit(cache=True)
def value_noise(x: float, y: float, z: float, cell_mm: float, seed: int) -> float:
    """Smooth (C1) value noise in [0, 1] with lattice spacing ``cell_mm``."""
    q0, q1, q2 = x / cell_mm, y / cell_mm, z / cell_mm
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
    return acc


@numba.njit(cache=True)
def fbm(x: float, y: float, z: float, cell_mm: float, seed: int, octaves: int) -> float:
    """Octaves of value noise, halving cell and amplitude each time; in [0, 1]."""
    total, amp, norm = 0.0, 1.0, 0.0
    for o in range(octaves):
        total += amp * value_noise(x, y, z, cell_mm / 2**o, seed + 101 * o)
        norm += amp
        amp *= 0.5
    return total / norm


@numba.njit(cache=True, inline="always")
def _ramp(v: float, lo: float, hi: float) -> float:
    return min(1.0, max(0.0, (v - lo) / (hi - lo)))


@numba.njit(cache=True)
def albedo(kind: int, x: float, y: float, z: float, seed: int, palette: np.ndarray) -> tuple[float, float, float]:
    """RGB albedo in [0, 1] of the point ``(x, y, z)`` (local mm).

    ``palette`` (3, 3) holds the colours of the ``NOISE`` kind (see :func:`palette`).
    """
    if kind == PLAIN:
        return PLAIN_RGB
    if kind == NOISE:
        # Two-colour fbm blotches (6 mm) with soft specks of a third colour (2 mm cells).
        mix = _ramp(fbm(x, y, z, 6.0, seed, 3), 0.1875, 0.8125)
        speck = 0.4 * _ramp(value_noise(x, y, z, 2.0, seed + 1), 0.66, 0.74)
        r = (1 - speck) * (mix * palette[0, 0] + (1 - mix) * palette[1, 0]) + speck * palette[2, 0]
        g = (1 - speck) * (mix * palette[0, 1] + (1 - mix) * palette[1, 1]) + speck * palette[2, 1]
        b = (1 - speck) * (mix * palette[0, 2] + (1 - mix) * palette[1, 2]) + speck * palette[2, 2]
        return r, g, b
    # The table: a grey 20 mm checker with ~1 mm soft edges, plus fine noise.
    s = np.sin(np.pi * x / 20.0) * np.sin(np.pi * y / 20.0)
    grey = 0.35 + 0.15 * _ramp(6.0 * s, -1.0, 1.0) + 0.2 * (fbm(x, y, z, 4.0, seed + 3, 2) - 0.5)
    return grey, 0.97 * grey, 0.93 * grey


def palette(seed: int) -> np.ndarray:
    """Three RGB colours (3, 3), deterministic from the seed."""
    return np.random.default_rng(seed + 7).uniform(0.15, 0.9, size=(3, 3))
