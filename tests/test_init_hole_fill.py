"""Enclosed holes of the init's depth and their harmonic fill (pipeline.init.hole_fill)."""
from __future__ import annotations

import numpy as np
import pytest

from init_scene import distance_to_spheres, make_scene
from pipeline.config.init import InitConfig, MVSConfig
from pipeline.errors import ConfigError
from pipeline.init import mvs
from pipeline.init.hole_fill import contradicted, enclosed_holes, flat_rimmed, harmonic_fill
from pipeline.init.io import DepthMap


def _valid_with_holes():
    valid = np.ones((40, 50), bool)
    valid[10:14, 10:13] = False  # enclosed, 12 px
    valid[0:3, 30:33] = False  # touches the image border
    valid[25:35, 5:25] = False  # enclosed, 200 px: too large at max_px 100
    valid[20:23, 40:43] = False  # enclosed, but reaches the mask's edge below
    return valid


def test_only_small_gaps_surrounded_by_depth_are_holes():
    valid = _valid_with_holes()
    mask = np.ones_like(valid)
    mask[23:, 38:] = False
    holes = enclosed_holes(valid, 100, mask)
    expected = np.zeros_like(valid)
    expected[10:14, 10:13] = True
    assert np.array_equal(holes, expected)
    # Without a mask the gap at the mask's edge is enclosed too; a larger limit takes the big one.
    no_mask = enclosed_holes(valid, 100)
    assert no_mask[20:23, 40:43].all() and not no_mask[25:35, 5:25].any()
    assert enclosed_holes(valid, 200)[25:35, 5:25].all()
    assert not enclosed_holes(valid, 0).any()


def test_diagonal_contact_joins_two_gaps():
    """A gap that touches another only at a corner is one region (its ring would otherwise hold
    a pixel without depth)."""
    valid = np.ones((20, 20), bool)
    valid[5:8, 5:8] = False
    valid[8:10, 8:10] = False
    assert enclosed_holes(valid, 13)[5:10, 5:10].sum() == 13
    assert not enclosed_holes(valid, 12).any()


def test_a_gap_whose_rim_steps_is_not_filled():
    """A hole in a plane or on a sphere has a flat rim; a gap between a near and a far surface
    (a slot seen through) does not."""
    H, W = 40, 40
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    holes = np.zeros((H, W), bool)
    holes[15:25, 15:25] = True
    plane = np.stack([xs, ys, 500.0 + 0.5 * xs - 0.2 * ys], -1)
    sphere = np.stack([xs, ys, 500.0 - np.sqrt(60.0**2 - (xs - 20) ** 2 - (ys - 20) ** 2)], -1)
    step = plane.copy()
    step[:, 20:, 2] += 30.0  # the right half 30 units behind: a slot between two surfaces
    assert flat_rimmed(holes, plane, 0.02).sum() == 100
    assert flat_rimmed(holes, sphere, 0.02).sum() == 100
    assert not flat_rimmed(holes, step, 0.02).any()
    assert flat_rimmed(holes, step, 10.0).sum() == 100
    with pytest.raises(ValueError, match="points"):
        flat_rimmed(holes, plane[..., :2], 0.02)


def test_a_view_that_sees_past_or_in_front_of_a_point_contradicts_it():
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    T = np.eye(4)
    depth = np.zeros((100, 100))
    depth[:, :50] = 500.0  # left half: a surface at 500 mm; right half: no depth
    pts = np.array([[-10.0, 0.0, 500.5],  # on the surface (within 0.5%)
                    [-10.0, 0.0, 450.0],  # 50 mm in front of what the view sees: the view sees past it
                    [-10.0, 0.0, 560.0],  # behind it: the view sees something else there
                    [10.0, 0.0, 500.0],  # projects where the view has no depth
                    [0.0, 0.0, -10.0]])  # behind the camera
    got = contradicted(pts, [depth], K[None], T[None], 0.005)
    assert got.tolist() == [False, True, True, False, False]
    assert not contradicted(pts, [], K[:0], T[:0], 0.005).any()


def _jacobi_reference(z, holes, iters=20000):
    """The obviously-correct slow version: each hole pixel the mean of its four neighbours,
    repeated until nothing moves."""
    z = z.astype(np.float64).copy()
    z[holes] = z[~holes & (z > 0)].mean()
    rows, cols = np.nonzero(holes)
    for _ in range(iters):
        new = 0.25 * (z[rows - 1, cols] + z[rows + 1, cols] + z[rows, cols - 1] + z[rows, cols + 1])
        if np.max(np.abs(new - z[rows, cols])) < 1e-12:
            break
        z[rows, cols] = new
    return z


def test_harmonic_fill_matches_the_iterated_mean_and_keeps_planes():
    rng = np.random.default_rng(0)
    H, W = 30, 40
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    z = 500.0 + 10 * np.sin(xx / 5.0) + 0.02 * yy**2 + rng.normal(0, 0.1, (H, W))
    holes = np.zeros((H, W), bool)
    holes[5:12, 6:15] = True
    holes[12, 9] = True  # a notch
    holes[20:24, 25:34] = True
    filled = harmonic_fill(np.where(holes, 0.0, z), holes)
    assert np.allclose(filled, _jacobi_reference(np.where(holes, 0.0, z), holes), atol=1e-8)
    assert np.array_equal(filled[~holes], z[~holes])
    # A plane's depth is harmonic: filled exactly.
    plane = 600.0 + 0.7 * xx - 0.3 * yy
    assert np.allclose(harmonic_fill(np.where(holes, 0.0, plane), holes), plane, atol=1e-9)


def test_harmonic_fill_refuses_holes_it_cannot_bound():
    z = np.full((10, 10), 500.0)
    holes = np.zeros((10, 10), bool)
    holes[0, 4] = True
    with pytest.raises(ValueError, match="image border"):
        harmonic_fill(z, holes)
    holes[:] = False
    holes[4, 4] = True
    z[4, 5] = 0.0
    with pytest.raises(ValueError, match="no depth"):
        harmonic_fill(z, holes)
    with pytest.raises(ValueError, match="shape"):
        harmonic_fill(z, holes[:5])
    with pytest.raises(ValueError, match="shape"):
        enclosed_holes(holes, 10, holes[:5])


def test_filled_points_lie_on_the_surface():
    """Punch a hole into the exact depth of the sphere scene: the filled points come back on
    the sphere within the membrane's bound. Where the depth has Laplacian ~L (per pixel^2), the
    harmonic fill of a hole of half-width a pixels is off by at most |L| a^2 / 2 in depth (the
    maximum principle for Poisson's equation), and a point's distance to the surface is at
    most its error along the ray."""
    scene, gt = make_scene(200, 150)
    i = 0
    valid = gt[i] > 0
    punched = valid.copy()
    ys, xs = np.nonzero(valid)
    cy, cx = int(np.median(ys)), int(np.median(xs))
    punched[cy - 4 : cy + 4, cx - 5 : cx + 5] = False
    depth = DepthMap(scene.view_ids[i], np.where(punched, gt[i], 0).astype(np.float32),
                     punched.astype(np.float32), punched, scene.K[i], scene.world_to_cam[i])
    pts = mvs.filled_hole_points(scene, i, depth, punched, 0.01, 0.02, [np.where(punched, gt[i], 0.0), gt[1], gt[2]])
    assert len(pts.pixels) == 80 and pts.valid.sum() == 80 and (pts.count == 0).all()
    err = distance_to_spheres(pts.points_mm, scene)
    z = gt[i][cy - 6 : cy + 6, cx - 7 : cx + 7].astype(np.float64)
    lap = np.abs(z[:-2, 1:-1] + z[2:, 1:-1] + z[1:-1, :-2] + z[1:-1, 2:] - 4 * z[1:-1, 1:-1]).max()
    assert err.max() <= lap * 4**2 / 2 + 1e-3, (err.max(), lap)
    ring = (pts.pixels[:, 0] == cy - 4) | (pts.pixels[:, 0] == cy + 3) | (pts.pixels[:, 1] == cx - 5) | (pts.pixels[:, 1] == cx + 4)
    assert err[ring].mean() < err[~ring].mean()  # pinned at the border, sagging inside


def test_mvs_cloud_gains_the_filled_points():
    scene, gt = make_scene(200, 150)
    base = mvs.run(scene, InitConfig.default(mvs=MVSConfig.default(hole_fill_area=0.0)))
    cfg = InitConfig.default(mvs=MVSConfig.default(hole_fill_area=0.01))
    filled = mvs.run(scene, cfg)
    assert sum(filled.info["hole_filled_pixels"]) > 0
    assert "hole_filled_pixels" in base.info and base.info["hole_filled_pixels"] == []
    # The depth maps stay the two-view-confirmed ones; the cloud grows and stays on the surface.
    for a, b in zip(base.depths, filled.depths):
        assert np.array_equal(a.depth_mm, b.depth_mm)
    assert len(filled.cloud.points_mm) > len(base.cloud.points_mm)
    assert np.median(distance_to_spheres(filled.cloud.points_mm, scene)) < 0.5


@pytest.mark.parametrize("kw", [{"hole_fill_area": -0.1}, {"hole_fill_area": 1.0}, {"hole_fill_max_bend": -1.0}])
def test_bad_hole_fill_settings_are_named(kw):
    with pytest.raises(ConfigError, match="hole_fill"):
        MVSConfig.default(**kw)
