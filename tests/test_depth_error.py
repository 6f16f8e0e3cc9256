"""Input-view depth error (pipeline.evaluation.depth_error) against a plain per-pixel count."""
import math

import numpy as np
import pytest

from pipeline.evaluation.depth_error import MAX_ERR_MM, depth_errors, gt_depths_mm


def test_figures_match_a_pixel_by_pixel_count():
    rng = np.random.default_rng(0)
    gt = rng.uniform(600, 700, (2, 20, 30))
    gt[0, :2] = 0  # GT misses
    err = rng.normal(0.3, 0.8, gt.shape)
    err[1, 5, :4] = [-12.0, 9.0, 6.0, -7.0]  # other surfaces
    depth = gt + err
    depth[1, 10:] = 0  # no depth rendered there
    masks = np.ones_like(gt, bool)
    masks[:, :, -3:] = False
    got = depth_errors(depth, gt, masks)
    pairs = [(depth[v, y, x] - gt[v, y, x]) for v in range(2) for y in range(20) for x in range(30)
             if masks[v, y, x] and depth[v, y, x] > 0 and gt[v, y, x] > 0]
    near = [e for e in pairs if abs(e) <= MAX_ERR_MM]
    covered = sum(1 for v in range(2) for y in range(20) for x in range(30) if masks[v, y, x] and depth[v, y, x] > 0)
    assert got["coverage"] == pytest.approx(covered / masks.sum())
    assert got["median_abs_mm"] == pytest.approx(float(np.median(np.abs(pairs))))
    assert got["signed_median_mm"] == pytest.approx(float(np.median(near)))
    assert got["mean_abs_mm"] == pytest.approx(sum(abs(e) for e in near) / len(near))
    assert got["share_above_1mm"] == pytest.approx(sum(abs(e) > 1 for e in pairs) / len(pairs))
    assert got["outliers"] == pytest.approx(4 / len(pairs))
    assert got["outliers_in_front"] == pytest.approx(2 / len(pairs))
    far = [abs(e) for e in pairs if abs(e) > MAX_ERR_MM]
    assert got["outlier_error_share"] == pytest.approx(sum(far) / sum(abs(e) for e in pairs))
    assert 0.2 < got["signed_median_mm"] < 0.4  # the bias put in: behind the truth


def test_no_overlap_gives_nan_and_bad_shapes_are_refused():
    gt = np.full((1, 4, 4), 500.0)
    got = depth_errors(np.zeros_like(gt), gt)
    assert got["coverage"] == 0.0 and math.isnan(got["median_abs_mm"]) and math.isnan(got["signed_median_mm"])
    assert math.isnan(got["outliers_in_front"]) and math.isnan(got["outlier_error_share"])
    with pytest.raises(ValueError, match=r"\(N, H, W\)"):
        depth_errors(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(ValueError, match="masks must be"):
        depth_errors(gt, gt, np.ones((1, 4, 5), bool))


def test_gt_depth_of_a_fronto_parallel_plane_is_its_distance():
    # A square at z = 500 mm in front of a camera at the origin: every pixel that sees it has depth 500.
    V = np.array([[-400.0, -400.0, 500.0], [400.0, -400.0, 500.0], [400.0, 400.0, 500.0], [-400.0, 400.0, 500.0]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    K = np.array([[[100.0, 0.0, 15.5], [0.0, 100.0, 11.5], [0.0, 0.0, 1.0]]])
    d = gt_depths_mm(V, F, K, np.eye(4)[None], 32, 24)
    assert d.shape == (1, 24, 32) and np.allclose(d, 500.0, atol=1e-3)
