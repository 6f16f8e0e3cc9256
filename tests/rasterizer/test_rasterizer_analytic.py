"""Closed-form cases: one surfel facing the camera, a tilted surfel, two overlapping ones."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.rasterizer import Camera, Surfels, rasterize

BACKENDS = ["cpu", "reference"]
F, W, H, CX, CY = 20.0, 9, 7, 4.0, 3.0  # principal point on the centre of pixel (row 3, col 4)


def camera(near: float = 0.5, far: float = 50.0, world_to_cam=None) -> Camera:
    K = np.array([[F, 0, CX], [0, F, CY], [0, 0, 1]])
    return Camera(K=K, world_to_cam=np.eye(4) if world_to_cam is None else world_to_cam, width=W, height=H, near=near, far=far)


def surfels(means, quats, scales, opacities, features) -> Surfels:
    t = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64))  # noqa: E731
    return Surfels(t(means), t(quats), t(scales), t(opacities), t(features))


def quat_about_x(angle: float) -> list[float]:
    return [math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_surfel_facing_camera(backend):
    d, o, s = 4.0, 0.6, 0.3
    out = rasterize(surfels([[0, 0, d]], [[1, 0, 0, 0]], [[s, s]], [o], [[0.2, 0.7, 1.0]]), camera(), backend, depth_eps=0)
    r, c = int(CY), int(CX)
    assert out.alpha[r, c].item() == pytest.approx(o, rel=1e-12)
    assert out.features[r, c].tolist() == pytest.approx([o * 0.2, o * 0.7, o * 1.0], rel=1e-12)
    assert out.depth_expected[r, c].item() == pytest.approx(d, rel=1e-12)
    assert out.depth_median[r, c].item() == pytest.approx(d, rel=1e-12)
    # Normal +z (away from the camera) is flipped to face it.
    assert (out.normal_cam[r, c] / o).tolist() == pytest.approx([0, 0, -1], abs=1e-12)
    assert (out.normal_world[r, c] / o).tolist() == pytest.approx([0, 0, -1], abs=1e-12)
    assert out.distortion[r, c].item() == pytest.approx(0, abs=1e-15)
    # One pixel right: the ray meets the plane at u = d / (F s); the low-pass term is 2.
    rho3, rho2 = (d / (F * s)) ** 2, 2.0
    assert out.alpha[r, c + 1].item() == pytest.approx(o * math.exp(-0.5 * min(rho3, rho2)), rel=1e-12)
    assert out.means2d[0].tolist() == pytest.approx([CX, CY], abs=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_world_normal_with_a_rotated_camera(backend):
    ang = 0.4  # camera rotated about its y axis, still looking at the surfel
    R = np.array([[math.cos(ang), 0, -math.sin(ang)], [0, 1, 0], [math.sin(ang), 0, math.cos(ang)]])
    p = np.array([1.0, 0.5, 5.0])
    w2c = np.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ p + np.array([0, 0, 4.0])  # the surfel centre lands at camera (0, 0, 4)
    q = [math.cos(0.3), 0, 0, math.sin(0.3)]  # about the world z axis: world normal stays (0, 0, 1)
    out = rasterize(surfels([p], [q], [[0.5, 0.5]], [0.8], [[1.0]]), camera(world_to_cam=w2c), backend)
    r, c = int(CY), int(CX)
    n_world = out.normal_world[r, c] / out.alpha[r, c]
    expected = np.array([0, 0, 1.0])
    if expected @ (p - (-R.T @ w2c[:3, 3])) > 0:  # facing the camera
        expected = -expected
    assert n_world.tolist() == pytest.approx(expected.tolist(), abs=1e-12)
    assert (out.normal_cam[r, c] / out.alpha[r, c]).tolist() == pytest.approx((R @ expected).tolist(), abs=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_tilted_surfel_depth_is_the_ray_plane_intersection(backend):
    d, tilt = 5.0, math.radians(40)
    out = rasterize(surfels([[0, 0, d]], [quat_about_x(tilt)], [[1.0, 1.0]], [0.9], [[1.0]]), camera(), backend, depth_eps=0)
    n = np.array([0, -math.sin(tilt), math.cos(tilt)])  # R_x(tilt) e_z
    for k in (-2, -1, 1, 2):  # pixels above and below the centre
        ray = np.array([0, k / F, 1.0])
        z = (n @ np.array([0, 0, d])) / (n @ ray)
        depth = out.depth_expected[int(CY) + k, int(CX)].item()
        assert depth == pytest.approx(z, rel=1e-10)
        assert abs(depth - d) > 0.05  # clearly not the centre depth
        assert out.depth_median[int(CY) + k, int(CX)].item() == pytest.approx(z, rel=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("o1", [0.3, 0.7])
def test_two_overlapping_surfels(backend, o1):
    d1, d2, o2, near, far = 3.0, 4.5, 0.8, 0.5, 50.0
    f1, f2 = [1.0, 0.0], [0.0, 1.0]
    # Listed back first: the renderer must sort by depth.
    s = surfels([[0, 0, d2], [0, 0, d1]], [[1, 0, 0, 0]] * 2, [[0.4, 0.4]] * 2, [o2, o1], [f2, f1])
    out = rasterize(s, camera(near, far), backend, depth_eps=0)
    r, c = int(CY), int(CX)
    w1, w2 = o1, (1 - o1) * o2
    assert out.features[r, c].tolist() == pytest.approx([w1, w2], rel=1e-12)
    assert out.alpha[r, c].item() == pytest.approx(1 - (1 - o1) * (1 - o2), rel=1e-12)
    assert out.depth_expected[r, c].item() == pytest.approx((w1 * d1 + w2 * d2) / (w1 + w2), rel=1e-12)
    # The median is the last surfel composited while T > 0.5.
    assert out.depth_median[r, c].item() == pytest.approx(d2 if 1 - o1 > 0.5 else d1, rel=1e-12)
    m = lambda z: far / (far - near) * (1 - near / z)  # noqa: E731
    assert out.distortion[r, c].item() == pytest.approx(w1 * w2 * (m(d1) - m(d2)) ** 2, rel=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_uncovered_pixel_follows_the_eps_rule(backend):
    s = surfels([[0, 0, 4.0]], [[1, 0, 0, 0]], [[0.05, 0.05]], [0.9], [[1.0]])
    for eps in (1e-6, 0.0):
        out = rasterize(s, camera(), backend, depth_eps=eps)
        assert out.alpha[0, 0].item() == 0.0
        assert out.depth_expected[0, 0].item() == 0.0 if eps > 0 else math.isnan(out.depth_expected[0, 0].item())
        assert out.depth_median[0, 0].item() == 0.0
        assert out.normal_cam[0, 0].tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_early_stop_drops_everything_behind(backend):
    """Alphas 0.99 (opacity 1, capped), 0.9, 0.95, 0.5 front to back: after two, T = 1e-3;
    the third would leave 5e-5 < 1e-4, so the pixel stops there: the third is dropped,
    and so is the fourth although 1e-3 * 0.5 alone would stay above 1e-4."""
    s = surfels([[0, 0, 2.0], [0, 0, 3.0], [0, 0, 4.0], [0, 0, 5.0]], [[1, 0, 0, 0]] * 4, [[0.5, 0.5]] * 4,
                [1.0, 0.9, 0.95, 0.5], np.eye(4))  # fmt: skip
    out = rasterize(s, camera(), backend)
    r, c = int(CY), int(CX)
    assert out.features[r, c].tolist() == pytest.approx([0.99, 0.01 * 0.9, 0.0, 0.0], rel=1e-12, abs=1e-15)
    assert out.alpha[r, c].item() == pytest.approx(1 - 0.01 * 0.1, rel=1e-12)
