"""The 3D labelling of a capture without masks (pipeline.labelling): the noise it measures,
the support it picks, the pieces it keeps, against known answers."""
from __future__ import annotations

import numpy as np
import pytest

from init_scene import make_scene
from pipeline import geometry
from pipeline import labelling as L


def test_refine_plane_measures_the_residuals_spread_whatever_the_first_band():
    """A plane with Gaussian residuals (sigma 0.8 mm) among outliers: refined from a band
    far narrower than the noise (0.1 mm) the measured sigma still comes out near 0.8, and
    the plane itself within a fraction of it."""
    rng = np.random.default_rng(0)
    n = np.array([0.1, -0.2, 0.97])
    n /= np.linalg.norm(n)
    u, v = L.plane_axes(n)
    pts = rng.uniform(-200, 200, (20000, 1)) * u + rng.uniform(-200, 200, (20000, 1)) * v
    pts += (30.0 + rng.normal(0.0, 0.8, (20000, 1))) * n
    pts = np.concatenate([pts, rng.uniform(-200, 200, (4000, 3))])
    plane, _ = L.fit_plane_ransac(pts, 0.1)
    plane, sigma = L.refine_plane(pts, plane, 0.1)
    assert sigma == pytest.approx(0.8, rel=0.15)
    assert abs(abs(plane[:3] @ n) - 1.0) < 1e-4 and abs(abs(plane[3]) - 30.0) < 0.1


def test_cross_view_noise_recovers_the_relative_noise_put_into_exact_depth():
    scene, depths = make_scene(160, 120)
    rng = np.random.default_rng(1)
    assert L.cross_view_noise(depths, scene.K, scene.world_to_cam) < 2e-4  # exact: the pixel grid only
    noisy = np.where(depths > 0, depths * (1.0 + 0.002 * rng.standard_normal(depths.shape)), 0.0)
    # Two views' independent noise: the difference's spread is sqrt(2) x each.
    assert L.cross_view_noise(noisy, scene.K, scene.world_to_cam) == pytest.approx(0.002 * np.sqrt(2), rel=0.2)


def test_up_is_orthogonal_to_every_level_image_axis():
    """Cameras on a ring, each rolled 0 degrees and pitched down 20-60 degrees: up is the
    ring's axis; all x axes parallel (cameras on a line, one orientation): up is left
    undetermined by them, and the images' up is taken."""
    up = np.array([0.3, -0.5, 0.81])
    up /= np.linalg.norm(up)
    a, b = L.plane_axes(up)
    Ts = []
    for k, (yaw, pitch) in enumerate([(0, 20), (50, 40), (110, 60), (200, 30)]):
        f = np.cos(np.radians(yaw)) * a + np.sin(np.radians(yaw)) * b  # horizontal forward
        fwd = np.cos(np.radians(pitch)) * f - np.sin(np.radians(pitch)) * up
        x = np.cross(fwd, up)
        x /= np.linalg.norm(x)
        y = np.cross(fwd, x)  # image down
        T = np.eye(4)
        T[:3, :3] = np.stack([x, y, fwd])
        T[:3, 3] = -T[:3, :3] @ (-500.0 * fwd)
        Ts.append(T)
    Ts = np.stack(Ts)
    assert L.up_direction(Ts) @ up > 1 - 1e-9
    line = np.stack([Ts[1]] * 3)
    line[:, :3, 3] += np.arange(3)[:, None] * 10.0
    assert L.up_direction(line) @ (-line[0, 1, :3]) > 1 - 1e-9


def test_connected_pieces_link_within_one_cell():
    pts = np.array([[0.0, 0, 0], [0.9, 0, 0], [1.8, 0.5, 0], [5.0, 0, 0], [5.5, 0.2, 0.1]])
    piece = L.connected_pieces(pts, 1.0)
    assert piece[0] == piece[1] == piece[2] and piece[3] == piece[4] and piece[0] != piece[3]


def test_the_labelling_is_the_same_at_any_world_scale():
    """Every tolerance is relative to the scene (its radius, voxel, measured noise): the same
    capture in micrometres (x1000) is labelled pixel for pixel as in mm."""
    scene, depths = make_scene(160, 120)
    labels = []
    for s in (1.0, 1000.0):
        T = scene.world_to_cam.copy()
        T[:, :3, 3] *= s
        S = scene.norm_to_world.copy()
        S[:3] *= s
        S[3, 3] = 1.0
        labels.append(L.label_scene(depths * s, scene.K, T, S, 0.003 * S[0, 0], 0.008 * S[0, 0]))
    assert np.array_equal(labels[0].pixel_labels, labels[1].pixel_labels)
    assert labels[1].region.radius_mm == pytest.approx(1000.0 * labels[0].region.radius_mm, rel=1e-9)
    assert (labels[0].pixel_labels == L.OBJECT).sum() > 1000


def test_seen_through_points_are_refuted_by_a_view_looking_past_them():
    scene, depths = make_scene(160, 120)
    K, T = scene.K, scene.world_to_cam
    d0 = depths[0]
    ys, xs = np.nonzero(d0 > 0)
    real = geometry.backproject_depth(K[0], T[0], d0)[ys, xs]
    floating = geometry.backproject_depth(K[0], T[0], 0.8 * d0)[ys, xs]  # 20% nearer: free space
    pts = np.concatenate([real, floating])
    src = np.zeros(len(pts), int)
    out = L.seen_through(pts, src, depths, K, T, 0.005)
    assert out[:len(real)].mean() < 0.01 and out[len(real):].mean() > 0.5
