"""Degenerate and extreme inputs: every output and gradient stays finite."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from raster_helpers import MAPS, PARAMS, random_camera, random_surfels, render_and_grads

from pipeline.rasterizer import Camera, Surfels

SCENE = 5.0  # the test scene spans depths 2-5
MEANS = [[0, 0, 3], [0.2, 0.1, 3.5], [-0.3, 0.2, 4], [0.1, -0.2, 2.5], [0, 0, 5]]
FACING = [[1.0, 0, 0, 0]] * 5
TILTED = [[0.9, 0.3, 0.2, 0.1]] * 5
EDGE_ON = [[math.cos(math.pi / 4), 0, math.sin(math.pi / 4), 0]] * 5  # normal along x


def cam(width=32, height=24, near=0.1, far=1e5) -> Camera:
    return Camera(K=np.array([[30.0, 0, width / 2], [0, 30.0, height / 2], [0, 0, 1]]), world_to_cam=np.eye(4),
                  width=width, height=height, near=near, far=far)  # fmt: skip


def surfels(means, quats, scales, opacities, dtype) -> Surfels:
    P = len(means)
    t = lambda x, shape: torch.as_tensor(np.asarray(x, dtype=np.float64).reshape(shape), dtype=dtype)  # noqa: E731
    feats = torch.linspace(0, 1, P * 3, dtype=dtype).reshape(P, 3)
    return Surfels(t(means, (P, 3)), t(quats, (P, 4)), t(scales, (P, 2)), t(opacities, (P,)), feats)


CASES = {
    "scales 1e-7 x scene": (MEANS, TILTED, [[1e-7 * SCENE] * 2] * 5, [0.7] * 5, cam(), True),
    "scales 1e3 x scene": (MEANS, TILTED, [[1e3 * SCENE, 0.5e3 * SCENE]] * 5, [0.7] * 5, cam(), True),
    "opacity 0 and 1": (MEANS, FACING, [[0.3, 0.2]] * 5, [0, 1, 0, 1, 0.5], cam(), True),
    "plane parallel to the ray": ([[0, 0, 3]] * 5, EDGE_ON, [[0.3, 0.2]] * 5, [0.7] * 5, cam(), True),
    "planes nearly parallel": (MEANS, [[math.cos(math.pi / 4 - 1e-9), 0, math.sin(math.pi / 4 - 1e-9), 0]] * 5,
                               [[0.3, 0.2]] * 5, [0.7] * 5, cam(), True),  # fmt: skip
    "at and behind the near plane": ([[0, 0, 0.1], [0, 0, 0.05], [0, 0, -1], [0.1, 0, 0.1000001], [0, 0, 0.2]],
                                     FACING, [[0.3, 0.2]] * 5, [0.7] * 5, cam(), True),  # fmt: skip
    "surfels 1e4 away": ([[0, 0, 1e4], [1, 1, 1e4], [0, 0, 9e3], [0, 0, 1e4], [50, 0, 1e4]], TILTED, [[100, 100]] * 5,
                         [0.7] * 5, cam(), True),  # fmt: skip
    "zero surfels": (np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 2)), np.zeros(0), cam(), False),
    "1x1 image": (MEANS, TILTED, [[0.3, 0.2]] * 5, [0.7] * 5, cam(1, 1), True),
    "all outside the image": ([[50, 0, 3], [0, 50, 3], [-50, 0, 3], [0, -50, 3], [100, 100, 3]], FACING,
                              [[0.3, 0.2]] * 5, [0.7] * 5, cam(), False),  # fmt: skip
}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("backend", ["cpu", "reference"])
@pytest.mark.parametrize("case", list(CASES))
def test_finite_outputs_and_gradients(case, backend, dtype):
    means, quats, scales, opac, camera, drawn = CASES[case]
    s = surfels(means, quats, scales, opac, dtype)
    out, grads = render_and_grads(s, camera, backend)
    for k in MAPS:
        v = getattr(out, k)
        assert v.shape[:2] == (camera.height, camera.width), k
        assert torch.isfinite(v).all(), f"{k} has NaN/Inf"
    for k in list(PARAMS) + ["means2d"]:
        assert grads[k] is not None and torch.isfinite(grads[k]).all(), f"d/d{k} has NaN/Inf"
    assert (out.alpha.max() > 0).item() == drawn
    assert (out.alpha <= 1).all() and (out.alpha >= 0).all()


@pytest.mark.parametrize("backend", ["cpu", "reference"])
def test_near_plane_culls_and_clips(backend):
    """Centre behind the near plane: culled. Centre in front but the splat reaching
    behind it: pixels whose intersection is nearer than ``near`` are skipped."""
    camera = cam(near=1.0)
    behind = surfels([[0, 0, 0.9]], FACING[:1], [[0.3, 0.3]], [0.9], torch.float64)
    out, _ = render_and_grads(behind, camera, backend)
    assert out.alpha.max().item() == 0.0 and out.radii.tolist() == [0]
    # A steep plane through z = 1.2 at the centre, crossing z = near = 1 a few pixels up.
    steep = surfels([[0, 0, 1.2]], [[math.cos(0.6), math.sin(0.6), 0, 0]], [[2.0, 2.0]], [0.9], torch.float64)
    out, _ = render_and_grads(steep, camera, backend)
    col = out.depth_median[:, camera.width // 2]
    drawn = col[col > 0]
    assert drawn.numel() > 0 and drawn.min().item() >= 1.0
    assert (out.alpha[:, camera.width // 2] == 0).any()


def test_opaque_stacks_match_the_reference():
    """Layers at the alpha cap 0.99 behind each other (the backward's value-behind recursion
    would have divided by 1 - alpha = 0.01): gradients equal the reference's in float64."""
    camera = random_camera(24, 20, seed=3)
    s = random_surfels(40, camera, seed=4, scale=(0.3, 0.6), opacity=(0.995, 1.0))
    out_c, g_c = render_and_grads(s, camera, "cpu")
    out_r, g_r = render_and_grads(s, camera, "reference")
    assert (out_c.alpha > 0.99).float().mean() > 0.5  # the stacks are opaque
    for k in MAPS:
        torch.testing.assert_close(getattr(out_c, k), getattr(out_r, k), rtol=1e-9, atol=1e-9)
    for k in list(PARAMS) + ["means2d"]:
        torch.testing.assert_close(g_c[k], g_r[k], rtol=1e-7, atol=1e-9)
