"""The binning's per-tile test (``_kernels.tile_reached``): it never drops a tile where a pixel
could composite the surfel (against a brute force over the tile's pixels), it drops most of
those where none can, and lists binned with it render bit for bit as the whole boxes' lists."""
from __future__ import annotations

import math
import shutil

import numba
import numpy as np
import pytest
import torch
from raster_helpers import MAPS, PARAMS, random_camera, random_surfels, with_grad

from pipeline.rasterizer import Camera, Surfels, rasterize, simd
from pipeline.rasterizer import _kernels as K
from pipeline.rasterizer import cpu


def _scene(dtype=torch.float32) -> tuple[Surfels, Camera]:
    """Surfels of many sizes, a tenth of them seen edge-on (ill-conditioned conics), and two
    whose boxes span more than 64 tiles (tested tile by tile, not through the set-up's bits)."""
    cam = random_camera(200, 150, seed=4)
    s = random_surfels(400, cam, 3, seed=4, dtype=torch.float64, scale=(0.005, 0.5))
    quats, scales = s.quats.clone(), s.scales.clone()
    R, t = cam.world_to_cam[:3, :3].to(torch.float64), cam.world_to_cam[:3, 3].to(torch.float64)
    for i in range(0, 400, 10):  # normal perpendicular to the viewing ray (+- a hair)
        ray = R.T @ (R @ s.means[i] + t)  # the camera-frame centre, in world axes
        side = torch.linalg.cross(ray, torch.tensor([0.3, 1.0, 0.2], dtype=torch.float64))
        normal = side / side.norm() + 1e-4 * (i % 3 - 1) * ray / ray.norm()
        quats[i] = _quat_with_z_along(normal / normal.norm())
    scales[:2] = torch.tensor([[2.0, 1.5], [1.2, 2.5]], dtype=torch.float64)
    s = Surfels(s.means, quats, scales, s.opacities, s.features)
    return Surfels(*(getattr(s, k).to(dtype) for k in PARAMS)), cam


def _quat_with_z_along(n: torch.Tensor) -> torch.Tensor:
    """A unit quaternion (w, x, y, z) of a rotation taking e_z to ``n``."""
    z = torch.tensor([0.0, 0.0, 1.0], dtype=n.dtype)
    axis = torch.linalg.cross(z, n)
    s, c = axis.norm(), torch.dot(z, n)
    half = math.atan2(s.item(), c.item()) / 2
    axis = axis / s if s > 0 else torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype)
    return torch.cat([torch.tensor([math.cos(half)], dtype=n.dtype), math.sin(half) * axis])


@numba.njit(cache=False)
def _tiles_by_brute_force(geo, Tm, box, radii, round32, near):
    """Per drawn surfel and tile of its box: (surfel, tx, ty, reached by the test, some pixel
    centre passes the kernels' per-pair test in float64, the ellipse is well-conditioned)."""
    out = []
    for s in range(box.shape[0]):
        if radii[s] == 0:
            continue
        g = geo[s]
        conic = K.tile_conic(g, round32)
        x0, x1, y0, y1 = box[s, 0], box[s, 1], box[s, 2], box[s, 3]
        for ty in range(y0 // K.TILE, y1 // K.TILE + 1):
            for tx in range(x0 // K.TILE, x1 // K.TILE + 1):
                xa, xb = max(x0, tx * K.TILE), min(x1, tx * K.TILE + K.TILE - 1)
                ya, yb = max(y0, ty * K.TILE), min(y1, ty * K.TILE + K.TILE - 1)
                hit = False
                for py in range(ya, yb + 1):
                    dy = py - g[K.GEO_CY]
                    qr = (py * g[K.GEO_AY] + g[K.GEO_A0], py * g[K.GEO_AY + 1] + g[K.GEO_A0 + 1],
                          py * g[K.GEO_AY + 2] + g[K.GEO_A0 + 2])  # fmt: skip
                    for px in range(xa, xb + 1):
                        ok = K._pair(float(px), dy * dy, qr[0], qr[1], qr[2], g[K.GEO_AX], g[K.GEO_AX + 1],
                                     g[K.GEO_AX + 2], g[K.GEO_CX], g[K.GEO_RHO_MAX], g[K.GEO_DET], g[K.GEO_INV_DET],
                                     float(Tm[s, 8]), g[K.GEO_INV_ZC], near, g[K.GEO_OPACITY])[0]  # fmt: skip
                        hit = hit or ok
                reached = K.tile_reached(conic, float(xa), float(xb), float(ya), float(yb))
                out.append((s, tx, ty, reached, hit, conic[20]))
    return out


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_tile_with_a_candidate_pixel_is_dropped_and_most_without_are(dtype):
    s, cam = _scene(dtype)
    g = cpu.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    rows = np.array(_tiles_by_brute_force(g.geo, g.Tm, g.box, g.radii, dtype == torch.float32, cam.near))
    reached, hit, well_posed = rows[:, 3].astype(bool), rows[:, 4].astype(bool), rows[:, 5].astype(bool)
    assert (reached | ~hit).all(), f"{(~reached & hit).sum()} tiles with a candidate pixel dropped"
    assert (~reached).sum() >= 0.5 * (~hit).sum(), "the test drops at least half the tiles without a candidate"
    assert (~well_posed).any() and (~reached & ~hit).sum() > 50, "the scene has edge-on surfels and tiles to drop"
    # what the binning lists: the reached tiles, in each surfel's row-major tile order
    listed = np.diff(g.emit_start)
    per_surfel = np.bincount(rows[:, 0].astype(int), weights=reached, minlength=listed.shape[0])
    np.testing.assert_array_equal(listed, per_surfel)
    big = [i for i in range(2) if (g.box[i, 1] // 16 - g.box[i, 0] // 16 + 1) * (g.box[i, 3] // 16 - g.box[i, 2] // 16 + 1) > 64]
    assert big, "a box of more than 64 tiles"


def test_reach_bits_are_the_test_tile_by_tile():
    s, cam = _scene()
    g = cpu.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    rows = np.array(_tiles_by_brute_force(g.geo, g.Tm, g.box, g.radii, True, cam.near))
    for i in np.flatnonzero(g.radii > 0):
        x0, x1, y0, y1 = g.box[i]
        bits = int(K.reach_bits(x0, x1, y0, y1, g.geo[i], True))
        mine = rows[rows[:, 0] == i]
        if len(mine) == 1:
            assert bits == 1, "one tile: reached, untested"
        elif len(mine) > 64:
            assert bits == 2**64 - 1
        else:
            assert bits == sum(1 << k for k, r in enumerate(mine[:, 3]) if r), i


def _full_boxes(monkeypatch, module, name: str):
    """Bin through ``module.name`` as if every tile of every box were reached (all bits set,
    and ``rho_max`` huge in the copy of the rows the binning tests boxes of over 64 tiles on)."""
    original = getattr(module, name)

    def every_tile(*args):
        args = list(args)
        i = next(k for k, a in enumerate(args) if isinstance(a, np.ndarray) and a.dtype == np.uint64)
        args[i] = np.full_like(args[i], 2**64 - 1)
        rows = args[i + 1].copy()
        rows[:, K.GEO_RHO_MAX] = 1e30
        args[i + 1] = rows
        return original(*args)

    monkeypatch.setattr(module, name, every_tile)


def _maps_and_grads(s: Surfels, cam: Camera, backend: str) -> dict[str, torch.Tensor]:
    s = with_grad(s)
    out = rasterize(s, cam, backend)
    g = torch.Generator().manual_seed(2)
    cot = {k: torch.randn(getattr(out, k).shape, generator=g, dtype=torch.float64) for k in MAPS}
    sum((getattr(out, k) * cot[k].to(out.alpha.dtype)).sum() for k in MAPS).backward()
    return {k: getattr(out, k).detach() for k in MAPS} | {"d_" + k: getattr(s, k).grad for k in PARAMS}


BACKENDS = [("cpu", torch.float32), ("cpu", torch.float64)]
if shutil.which("c++") is not None:
    BACKENDS.append(("simd", torch.float32))


@pytest.mark.parametrize("backend,dtype", BACKENDS)
def test_lists_render_bit_for_bit_as_the_whole_boxes(monkeypatch, backend, dtype):
    from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels

    s, cam = _scene(dtype)
    dense_cam, n2w = dtu_camera(160, 120)
    dense = object_surfels(20000, n2w, seed=1)
    dense = Surfels(*(getattr(dense, k).to(dtype) for k in PARAMS))
    for scene, camera in ((s, cam), (dense, dense_cam)):
        culled = _maps_and_grads(scene, camera, backend)
        with monkeypatch.context() as m:
            if backend == "cpu":
                _full_boxes(m, K, "bin_tiles")
            else:
                _full_boxes(m, simd, "bin_tiles")
            whole = _maps_and_grads(scene, camera, backend)
            geom_whole = _prepare(backend, scene, camera)
        geom = _prepare(backend, scene, camera)
        assert geom.num_pairs < 0.95 * geom_whole.num_pairs, "the test drops entries"
        for k in culled:
            assert torch.equal(culled[k], whole[k]), k


def _prepare(backend: str, s: Surfels, cam: Camera) -> cpu.Geometry:
    if backend == "cpu":
        return cpu.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    return simd.prepare(s.means, s.quats, s.scales, s.opacities, s.features, cam)
