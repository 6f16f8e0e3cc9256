"""Default (NCC-patch) features, Vis-MVSNet preprocessing, and the GCF loss minimum at
the true depth on a rendered synthetic scene."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.priors.features import FeatureError, default_features, vismvsnet_input


def textured(h=40, w=60, seed=0):
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(rng.uniform(size=(h, w)).astype(np.float32), (0, 0), 1.5)
    g = (g - g.min()) / (g.max() - g.min())
    return np.repeat(g[..., None], 3, axis=2) * np.array([1.0, 0.9, 0.8], np.float32)


def test_shape_and_cosine_is_ncc():
    img = textured()
    f = default_features(img, patch=5, scales=(1,))
    assert f.shape == (25, 20, 30) and f.dtype == np.float32
    # At scale 1 the cosine of two feature vectors is the NCC of the 5x5 windows of the
    # half-resolution grey image.
    half = cv2.resize(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), (30, 20), interpolation=cv2.INTER_AREA)
    (y1, x1), (y2, x2) = (7, 9), (12, 21)
    a, b = half[y1 - 2:y1 + 3, x1 - 2:x1 + 3].ravel(), half[y2 - 2:y2 + 3, x2 - 2:x2 + 3].ravel()
    ncc = np.corrcoef(a, b)[0, 1]
    cos = f[:, y1, x1] @ f[:, y2, x2] / (np.linalg.norm(f[:, y1, x1]) * np.linalg.norm(f[:, y2, x2]))
    assert abs(cos - ncc) < 1e-5
    # Two scales: (patch^2 * 2) channels, unit norm where textured.
    f2 = default_features(img)
    assert f2.shape == (50, 20, 30)
    np.testing.assert_allclose(np.linalg.norm(f2, axis=0), 1.0, atol=1e-5)


def test_invariant_to_gain_and_offset():
    img = textured()
    f = default_features(img)
    g = default_features(0.6 * img + 0.15)
    np.testing.assert_allclose(f, g, atol=2e-4)


def test_flat_regions_and_bad_images():
    img = textured(41, 61)  # odd size: cropped to even before halving
    img[:, :30] = 0.5  # flat left part
    f = default_features(img)
    assert f.shape == (50, 20, 30) and np.all(np.isfinite(f))
    # Flat as far as each scale's patch reaches: 2 half-res pixels at scale 1, ~6 at scale 2.
    assert not np.any(f[:25, :, :12]) and not np.any(f[25:, :, :8]) and np.any(f[:, :, 20:])
    with pytest.raises(FeatureError, match="no textured pixel"):
        default_features(np.full((40, 60, 3), 0.3, np.float32), where="view 23")
    bad = textured()
    bad[3, 3, 1] = np.nan
    with pytest.raises(FeatureError, match="view 24: image has non-finite values"):
        default_features(bad, where="view 24")
    with pytest.raises(FeatureError, match=r"must be \(H, W, 3\)"):
        default_features(np.zeros((40, 60), np.float32))


def test_detrend_drops_ramps_and_keeps_texture():
    """A linear ramp of grey (shading on a plain surface) matches its own shifted copy under
    NCC: with ``detrend`` its patches are no information; texture keeps its features, and
    each kept feature is orthogonal to the patch's x and y ramps."""
    ys, xs = np.mgrid[0:40, 0:60].astype(np.float32)
    ramp = 0.2 + 0.01 * xs + 0.004 * ys
    ramp_img = np.repeat(ramp[..., None], 3, axis=2)
    plain = default_features(ramp_img, min_contrast=0.002)
    detrended = default_features(ramp_img, min_contrast=0.002, detrend=True)
    # Away from the borders (reflection bends the ramp there): the patch reach, plus the blur at scale 2.
    assert np.all(np.linalg.norm(plain[:, 4:-4, 4:-4], axis=0) > 0.99)
    assert not np.any(detrended[:25, 2:-2, 2:-2]) and not np.any(detrended[25:, 8:-8, 8:-8])
    img = textured()
    f = default_features(img, scales=(1,), detrend=True)
    kept = np.linalg.norm(f, axis=0) > 0
    assert kept.mean() > 0.95
    r = np.arange(-2, 3, dtype=np.float32)
    x_ramp, y_ramp = np.tile(r, 5), np.repeat(r, 5)  # channel c = (dy, dx) in row-major order
    np.testing.assert_allclose(np.einsum("chw,c->hw", f, x_ramp), 0.0, atol=1e-5)
    np.testing.assert_allclose(np.einsum("chw,c->hw", f, y_ramp), 0.0, atol=1e-5)
    # Texture on top of a ramp: the same features as the texture alone (the ramp is removed).
    g = default_features(img + 0.3 * ramp_img / ramp_img.max(), scales=(1,), detrend=True)
    both = kept & (np.linalg.norm(g, axis=0) > 0)
    cos = np.einsum("chw,chw->hw", f, g)[both]
    assert np.median(cos) > 0.99, np.median(cos)


def test_vismvsnet_preprocessing_is_bgr_imagenet():
    img = np.zeros((5, 7, 3), np.float32)
    img[..., 0] = 1.0  # pure red
    x = vismvsnet_input(img)
    assert x.shape == (1, 3, 4, 6)  # cropped to even size
    # Channel 2 is red (BGR order): (1 - 0.485) / 0.229; channel 0 is blue: -0.406 / 0.225.
    np.testing.assert_allclose(x[0, :, 0, 0], [-0.406 / 0.225, -0.456 / 0.224, (1 - 0.485) / 0.229], rtol=1e-6)


def test_gcf_minimum_at_true_depth(bundled_scan):
    """Eq. 4-9 on the default features: argmin over depth offsets within 1 mm of 0 on a
    rendered relief plate seen by scan24's cameras 23/24/33 at 200x150, with a
    different exposure per view."""
    from pipeline.benchmarks.gcf_offset import relief_curve

    deltas = np.arange(-10.0, 10.01, 1.0)
    curve, _ = relief_curve(bundled_scan, 200, 150, deltas)
    i = int(np.argmin(curve))
    assert abs(deltas[i]) <= 1.0
    assert min(curve[0], curve[-1]) > 1.5 * curve[i]  # a real basin, not a flat curve
    left, right = curve[: i + 1], curve[i:]
    assert np.all(np.diff(left) <= 1e-3) and np.all(np.diff(right) >= -1e-3)  # unimodal


def test_gcf_minimum_on_a_synth_scene(bundled_scan):
    """The same on `gcgs synth`'s synth_relief (one ray per pixel, no anti-aliasing) at
    200x150, where a pixel spans ~1.9 mm: argmin within 2 mm."""
    from pipeline.benchmarks.gcf_offset import synth_curve

    deltas = np.arange(-10.0, 10.01, 1.0)
    curve, _ = synth_curve("synth_relief", bundled_scan, 200, 150, deltas)
    i = int(np.argmin(curve))
    assert abs(deltas[i]) <= 2.0
    assert min(curve[0], curve[-1]) > 1.15 * curve[i]
