"""GCF loss (Eq. 4-9) and normal losses (Eq. 10-12): values against an independent
numpy implementation, edge cases, and float64 gradchecks."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage as ndi
import torch

from pipeline import geometry
from pipeline.losses import cosine, gcf_loss, normal_consistency_losses, sample_features, sobel


def look_at(center: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_to_cam of a camera at ``center`` looking at ``target`` (OpenCV axes)."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross([0.0, -1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z])
    T[:3, 3] = -T[:3, :3] @ center
    return T


@pytest.fixture()
def tiny():
    """A reference and two source cameras around a target 100 mm away; random features."""
    rng = np.random.default_rng(1)
    H, W = 6, 8
    K = np.array([[9.0, 0.0, 3.6], [0.0, 9.0, 2.4], [0.0, 0.0, 1.0]])
    target = np.array([0.0, 0.0, 100.0])
    cams = [look_at(np.array(c), target) for c in ([0.0, 0, 0], [15.0, 2, 3], [-12.0, -5, 4])]
    feats = [rng.normal(size=(4, H // 2, W // 2)) for _ in cams]
    depth = 100.0 + rng.uniform(-3, 3, size=(H, W))
    return H, W, K, cams, feats, depth


def reference_gcf(depth, K, cams, feats, image_size, valid=None, weight_depth=None, max_dissimilarity=None):
    """Loop-based Eq. 4-9 with scipy's bilinear interpolation (independent of torch), over
    the pixels in ``valid`` (default: all) whose reference feature is not zero; a zero
    source feature adds nothing. The view weights w come from ``weight_depth`` (default:
    ``depth``), so that finite differences with it fixed give the gradient of the loss
    whose weights are constants. Pairs with ``1 - cos >= max_dissimilarity`` add nothing."""
    H, W = depth.shape
    o = [geometry.camera_center(T) for T in cams]
    pts = geometry.backproject_depth(K, cams[0], depth).reshape(-1, 3)
    pts_w = geometry.backproject_depth(K, cams[0], depth if weight_depth is None else weight_depth).reshape(-1, 3)
    use = np.ones(H * W, bool) if valid is None else valid.reshape(-1).copy()
    s = feats[0].shape[2] / image_size[1]

    def bilinear(f, x, y):
        fx, fy = (x + 0.5) * s - 0.5, (y + 0.5) * s - 0.5
        if not (0 <= fx <= f.shape[2] - 1 and 0 <= fy <= f.shape[1] - 1):
            return None
        return np.array([ndi.map_coordinates(c, [[fy], [fx]], order=1)[0] for c in f])

    total = 0.0
    for n, x in enumerate(pts):
        if not use[n]:
            continue
        fr = bilinear(feats[0], n % W, n // W)
        if not np.any(fr):
            use[n] = False
            continue
        xw = pts_w[n]
        v_ref = (xw - o[0]) / np.linalg.norm(xw - o[0])
        for i in (1, 2):
            px, z = geometry.project(K, cams[i], x[None])
            if z[0] <= 0:
                continue
            fi = bilinear(feats[i], *px[0])
            if fi is None or not np.any(fi):
                continue
            v_i = (xw - o[i]) / np.linalg.norm(xw - o[i])
            w = max(0.0, v_ref @ v_i)
            dissimilarity = 1 - fr @ fi / (np.linalg.norm(fr) * np.linalg.norm(fi))
            if max_dissimilarity is None or dissimilarity < max_dissimilarity:
                total += w * dissimilarity
    return total / max(use.sum(), 1)


def test_gcf_matches_independent_reference(tiny):
    H, W, K, cams, feats, depth = tiny
    t = lambda a: torch.from_numpy(a)  # noqa: E731
    src = [(K, cams[i], t(feats[i])) for i in (1, 2)]
    got = gcf_loss(t(depth), K, cams[0], t(feats[0]), src, valid=np.ones((H, W), bool))
    want = reference_gcf(depth, K, cams, feats, (H, W))
    assert want > 0.1  # the reference is not trivially zero
    np.testing.assert_allclose(float(got), want, rtol=1e-9)


def test_gcf_consistent_features_give_zero_and_offsets_do_not():
    """Features that are a function of the 3D point give 0 loss at the true depth."""
    H, W = 24, 32
    K = np.array([[200.0, 0, 15.5], [0, 200.0, 11.5], [0, 0, 1]])  # 0.5 mm per pixel at 100 mm
    target = np.array([0.0, 0.0, 100.0])
    cams = [look_at(np.array(c), target) for c in ([0.0, 0, 0], [10.0, 0, 0], [0.0, 8, 0])]
    # Plane z = 100 (world); every view sees features f(X) of the plane point X at each
    # full-resolution pixel, so use the features at full resolution.
    feats = []
    for T in cams:
        ys, xs = np.mgrid[0:H, 0:W].astype(float)
        rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T @ T[:3, :3]
        o = geometry.camera_center(T)
        X = o + rays * ((100.0 - o[2]) / rays[..., 2])[..., None]
        feats.append(torch.from_numpy(np.stack([np.sin(X[..., 0]), np.cos(X[..., 1] * 1.3), np.sin(X[..., 0] - X[..., 1])])))
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    depth = 100.0 / (np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T @ cams[0][:3, :3])[..., 2]
    depth = torch.from_numpy(depth)
    src = [(K, cams[i], feats[i]) for i in (1, 2)]
    everywhere = torch.ones(H, W, dtype=torch.bool)
    l0 = float(gcf_loss(depth, K, cams[0], feats[0], src, valid=everywhere))
    l5 = float(gcf_loss(depth + 5.0, K, cams[0], feats[0], src, valid=everywhere))
    assert l0 < 1e-3 and l5 > 0.1


def test_gcf_drops_outlier_pairs(tiny):
    """With ``max_dissimilarity`` the (point, source) pairs whose features disagree that much
    add neither loss nor gradient (FatesGS's outlier rule); the rest match the reference."""
    H, W, K, cams, feats, depth = tiny
    t = torch.from_numpy
    src = [(K, cams[i], t(feats[i])) for i in (1, 2)]
    valid = np.ones((H, W), bool)
    for cut in (0.5, 1.0, 2.0):
        got = float(gcf_loss(t(depth), K, cams[0], t(feats[0]), src, valid=valid, max_dissimilarity=cut))
        np.testing.assert_allclose(got, reference_gcf(depth, K, cams, feats, (H, W), max_dissimilarity=cut), rtol=1e-9)
    all_pairs = float(gcf_loss(t(depth), K, cams[0], t(feats[0]), src, valid=valid))
    half = float(gcf_loss(t(depth), K, cams[0], t(feats[0]), src, valid=valid, max_dissimilarity=0.5))
    assert half < 0.5 * all_pairs  # random features: most pairs are outliers
    # A point whose every pair is an outlier gets no gradient.
    d = t(depth).requires_grad_()
    loss, terms, points = gcf_loss(d, K, cams[0], t(feats[0]), src, valid=valid, max_dissimilarity=0.5,
                                   return_terms=True)
    g, = torch.autograd.grad(loss, d)
    dead = torch.zeros(H * W, dtype=torch.bool)
    dead[torch.nonzero(points.reshape(-1)).squeeze(1)[terms.detach() == 0]] = True
    assert dead.any() and torch.count_nonzero(g.reshape(-1)[dead]) == 0


def test_gcf_ignores_points_behind_or_outside_sources(tiny):
    H, W, K, cams, feats, depth = tiny
    t = torch.from_numpy
    away = look_at(np.array([0.0, 0.0, 300.0]), np.array([0.0, 0.0, 400.0]))  # looks away
    far_side = look_at(np.array([500.0, 0.0, 100.0]), np.array([600.0, 0.0, 100.0]))
    loss = gcf_loss(t(depth), K, cams[0], t(feats[0]), [(K, away, t(feats[1])), (K, far_side, t(feats[2]))],
                    valid=np.ones((H, W), bool))
    assert float(loss) == 0.0
    # Pixels outside the mask (whatever their depth, NaN included) and depth-0 pixels are
    # not points; a NaN inside the mask is an error, not a silently dropped pixel.
    d = depth.copy()
    d[0, 0], d[1, 1] = 0.0, np.nan
    mask = np.ones((H, W), bool)
    mask[1] = False
    src = [(K, cams[i], t(feats[i])) for i in (1, 2)]
    _, terms, points = gcf_loss(t(d), K, cams[0], t(feats[0]), src, valid=torch.from_numpy(mask), return_terms=True)
    # Points: in the mask, depth > 0, and inside the 1/2-resolution feature map (its
    # centres span image pixels 0.5 .. W - 1.5, so the outermost ring of pixels is out).
    expect = np.zeros((H, W), bool)
    expect[1:-1, 1:-1] = True
    expect &= mask
    assert torch.equal(points, torch.from_numpy(expect)) and terms.shape == (expect.sum(),)
    assert torch.isfinite(terms).all()
    with pytest.raises(ValueError, match="non-finite depth inside the validity mask"):
        gcf_loss(t(d), K, cams[0], t(feats[0]), src, valid=np.ones((H, W), bool))
    with pytest.raises(ValueError, match="shape"):
        gcf_loss(t(depth), K, cams[0], t(feats[0]), src, valid=np.ones((H, W + 1), bool))


def test_gcf_faint_alpha_pixels_are_not_points(tiny):
    """A rendered expected depth is positive wherever alpha is faint; with the validity
    mask (alpha > 0.5) those pixels must not count, though their depth is positive."""
    H, W, K, cams, feats, depth = tiny
    t = torch.from_numpy
    alpha = np.full((H, W), 0.9)
    alpha[:, :3] = 0.02  # faint: a far-away floater's expected depth, say
    rendered = depth.copy()
    rendered[:, :3] = 40.0  # positive, and nowhere near the surface
    valid = alpha > 0.5
    src = [(K, cams[i], t(feats[i])) for i in (1, 2)]
    got = float(gcf_loss(t(rendered), K, cams[0], t(feats[0]), src, valid=t(valid)))
    want = reference_gcf(rendered, K, cams, feats, (H, W), valid)
    np.testing.assert_allclose(got, want, rtol=1e-9)
    # The same render counted everywhere (what a depth > 0 test would do) is another loss.
    everywhere = float(gcf_loss(t(rendered), K, cams[0], t(feats[0]), src, valid=np.ones((H, W), bool)))
    assert abs(everywhere - got) > 0.05
    # Only the masked pixels get a gradient.
    d = t(rendered).requires_grad_()
    g, = torch.autograd.grad(gcf_loss(d, K, cams[0], t(feats[0]), src, valid=t(valid)), d)
    assert torch.count_nonzero(g[:, :3]) == 0 and torch.count_nonzero(g[:, 3:]) > 0


def test_zero_features_have_defined_cosine_and_finite_gradients(tiny):
    a = torch.zeros(5, 3, requires_grad=True)
    b = torch.randn(5, 3, requires_grad=True)
    c = cosine(a, b)
    assert torch.equal(c, torch.zeros(3))
    c.sum().backward()
    assert torch.isfinite(a.grad).all() and torch.isfinite(b.grad).all()
    assert torch.allclose(cosine(b, 2 * b), torch.ones(3))
    # Flat (zero) regions in the features: the loss and its depth gradient stay finite.
    H, W, K, cams, feats, depth = tiny
    feats = [f.copy() for f in feats]
    feats[0][:, :, :2] = 0.0
    feats[1][:, 1:, :] = 0.0
    t = torch.from_numpy
    d = t(depth).requires_grad_()
    loss = gcf_loss(d, K, cams[0], t(feats[0]), [(K, cams[i], t(feats[i])) for i in (1, 2)],
                    valid=np.ones((H, W), bool))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(d.grad).all()


def test_sample_features_pixel_centres():
    """A 1/2-resolution map has its centre j at image x = 2j + 0.5."""
    f = torch.arange(12.0).view(1, 3, 4)  # h=3, w=4 of an image 6 x 8
    pix = torch.tensor([[0.5, 0.5], [2.5, 0.5], [1.5, 0.5], [6.5, 4.5], [0.4, 0.5], [6.6, 0.5]])
    vals, inside = sample_features(f, pix, (6, 8))
    np.testing.assert_allclose(vals[0, :4].numpy(), [0.0, 1.0, 0.5, 11.0], atol=1e-6)
    assert inside.tolist() == [True, True, True, True, False, False]


def test_gcf_gradient_matches_reference_with_constant_weights(tiny):
    """The depth gradient is the finite-difference gradient of the reference loss with the
    view weights w held at the current depth (w is a confidence, not a target)."""
    H, W, K, cams, feats, depth = tiny
    feats = [f.copy() for f in feats]
    feats[0][:, :2, :3] = 0.0  # flat at image pixels rows 1-2, columns 1-4: no gradient there
    t = torch.from_numpy
    src = [(t(K), t(cams[i]), t(feats[i])) for i in (1, 2)]
    d = t(depth).requires_grad_()
    g, = torch.autograd.grad(gcf_loss(d, K, cams[0], t(feats[0]), src, valid=np.ones((H, W), bool)), d)
    eps = 1e-5
    fd = np.zeros_like(depth)
    for k in range(depth.size):
        step = np.zeros_like(depth)
        step.flat[k] = eps
        fd.flat[k] = (reference_gcf(depth + step, K, cams, feats, (H, W), weight_depth=depth)
                      - reference_gcf(depth - step, K, cams, feats, (H, W), weight_depth=depth)) / (2 * eps)
    np.testing.assert_allclose(g.numpy(), fd, atol=1e-7, rtol=1e-4)
    assert torch.count_nonzero(g) >= H * W // 3  # depth really drives the loss
    assert torch.count_nonzero(g[1:3, 1:5]) == 0 and torch.count_nonzero(g[3, 1:5]) == 4
    # With the weights' own gradient (the undetached w) the result would differ:
    with_w = np.zeros_like(depth)
    for k in range(depth.size):
        step = np.zeros_like(depth)
        step.flat[k] = eps
        with_w.flat[k] = (reference_gcf(depth + step, K, cams, feats, (H, W))
                          - reference_gcf(depth - step, K, cams, feats, (H, W))) / (2 * eps)
    assert np.abs(with_w - fd).max() > 1e-3 * np.abs(fd).max()


def test_gcf_flat_features_neither_count_nor_pull():
    """Textureless everywhere (all-zero features): no point, loss 0 and no depth gradient,
    rather than a loss equal to the view weight that pulls depth towards the cameras."""
    H, W = 6, 8
    K = np.array([[9.0, 0.0, 3.6], [0.0, 9.0, 2.4], [0.0, 0.0, 1.0]])
    target = np.array([0.0, 0.0, 100.0])
    cams = [look_at(np.array(c), target) for c in ([0.0, 0, 0], [15.0, 2, 3], [-12.0, -5, 4])]
    zero = torch.zeros(4, H // 2, W // 2, dtype=torch.float64)
    rich = torch.from_numpy(np.random.default_rng(0).normal(size=(4, H // 2, W // 2)))
    d = torch.full((H, W), 100.0, dtype=torch.float64, requires_grad=True)
    for ref, srcf in ((zero, rich), (rich, zero)):
        loss, terms, points = gcf_loss(d, K, cams[0], ref, [(K, cams[i], srcf) for i in (1, 2)],
                                       valid=np.ones((H, W), bool), return_terms=True)
        g, = torch.autograd.grad(loss, d)
        assert float(loss.detach()) == 0.0 and torch.count_nonzero(g) == 0
        assert int(points.sum()) == (0 if ref is zero else (H - 2) * (W - 2))  # the ring is off the map


def test_normal_losses_values():
    rng = np.random.default_rng(0)
    H, W = 7, 9
    n_prior = torch.from_numpy(rng.normal(size=(3, H, W)))
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[0, 0] = False
    # A constant offset: L_nc is its L1 norm, L_ngc is 0 (no gradient difference).
    off = torch.tensor([0.1, -0.2, 0.05], dtype=torch.float64).view(3, 1, 1)
    l_nc, l_ngc = normal_consistency_losses(n_prior + off, n_prior, mask)
    assert abs(float(l_nc) - 0.35) < 1e-12 and abs(float(l_ngc)) < 1e-20
    # A ramp of slope a per pixel in x on channel 0: Sobel/8 gives a; L_ngc = a^2 where
    # the whole 3x3 neighbourhood is valid.
    a = 0.03
    ramp = torch.zeros(3, H, W, dtype=torch.float64)
    ramp[0] = a * torch.arange(W, dtype=torch.float64)
    l_nc, l_ngc = normal_consistency_losses(n_prior + ramp, n_prior, mask)
    want_nc = float((a * torch.arange(W, dtype=torch.float64)).expand(H, W)[mask].mean())
    assert abs(float(l_nc) - want_nc) < 1e-12
    assert abs(float(l_ngc) - a * a) < 1e-12
    # Invalid pixels with garbage do not leak in.
    n_render = n_prior + ramp
    n_render[:, 0, 0] = 1e6
    assert abs(float(normal_consistency_losses(n_render, n_prior, mask)[1]) - a * a) < 1e-12
    assert torch.allclose(sobel(ramp)[0, 0, 1:-1, 1:-1], torch.full((H - 2, W - 2), a, dtype=torch.float64))


def test_normal_losses_gradcheck():
    rng = np.random.default_rng(3)
    n_r = torch.from_numpy(rng.normal(size=(3, 6, 7))).requires_grad_()
    n_p = torch.from_numpy(rng.normal(size=(3, 6, 7)))
    mask = torch.from_numpy(rng.uniform(size=(6, 7)) > 0.2)
    assert torch.autograd.gradcheck(lambda x: normal_consistency_losses(x, n_p, mask), (n_r,), eps=1e-6, atol=1e-7)


def test_normal_losses_shape_errors():
    with pytest.raises(ValueError, match="must both be"):
        normal_consistency_losses(torch.zeros(3, 4, 5), torch.zeros(3, 4, 6), torch.ones(4, 5, dtype=torch.bool))
