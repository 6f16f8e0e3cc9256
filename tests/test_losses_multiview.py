"""PGSR multi-view consistency (pipeline.losses.multiview): homographies against ray-plane
intersection, the loss against a loop-based numpy reference, float64 gradchecks, the
minimum at the true plane of an analytic textured-plane scene, bad input, and the
forward-backward occlusion check."""
from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch

from pipeline.losses.multiview import (
    _patch_moments,
    MIN_Z,
    SourceView,
    best_source_ncc,
    multiview_consistency,
    plane_homographies,
    reference_pixels,
    textured_pixels,
)


# ----------------------------------------------------------------------------- helpers
def rot(axis, deg: float) -> np.ndarray:
    """Rotation matrix about ``axis`` by ``deg`` degrees (Rodrigues)."""
    k = np.asarray(axis, float)
    k = k / np.linalg.norm(k)
    a = math.radians(deg)
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(a) * Kx + (1 - math.cos(a)) * Kx @ Kx


def orbit(target: np.ndarray, axis, deg: float) -> np.ndarray:
    """ref_to_src of a camera obtained by rotating the reference camera (at the origin,
    identity orientation) about ``target`` by ``deg`` about ``axis``."""
    R_c2r = rot(axis, deg)
    c = target - R_c2r @ target
    T = np.eye(4)
    T[:3, :3] = R_c2r.T
    T[:3, 3] = -R_c2r.T @ c
    return T


def scale_K(K_train: np.ndarray, s: float) -> np.ndarray:
    """Full-resolution intrinsics ``S @ K_train`` for an integer upscale ``s``."""
    S = np.array([[s, 0, 0.5 * s - 0.5], [0, s, 0.5 * s - 0.5], [0, 0, 1.0]])
    return S @ K_train


def plane_depth(K: np.ndarray, T: np.ndarray, n: np.ndarray, rho: float, h: int, w: int) -> np.ndarray:
    """``(h, w)`` camera-frame depth of the plane ``n . X = rho`` (reference frame) seen by
    the camera ``T`` (reference -> camera) with intrinsics ``K``, by ray-plane intersection."""
    R, t = T[:3, :3], T[:3, 3]
    n_c = R @ n
    rho_c = rho + n_c @ t  # n . R^T (X_c - t) = rho
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T  # z = 1
    return rho_c / (rays @ n_c)


def t64(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x), dtype=torch.float64)


def all_pixels(h: int, w: int) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1)], -1)


# ------------------------------------------------------------ slow numpy reference
def bilinear_np(img: np.ndarray, x: float, y: float) -> float:
    """Bilinear value at (x, y) in [0, W-1] x [0, H-1], integer pixel centres."""
    H, W = img.shape
    x0, y0 = min(math.floor(x), W - 2), min(math.floor(y), H - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


def depth_lookup_np(D: np.ndarray, x: float, y: float) -> float | None:
    """Bilinear depth if all four neighbours have depth, else the nearest pixel's, else None."""
    h, w = D.shape
    if 0 <= x <= w - 1 and 0 <= y <= h - 1:
        x0, y0 = min(math.floor(x), w - 2), min(math.floor(y), h - 2)
        if (D[y0:y0 + 2, x0:x0 + 2] > 0).all():
            return bilinear_np(D, x, y)
    xn, yn = math.floor(x + 0.5), math.floor(y + 0.5)
    if 0 <= xn < w and 0 <= yn < h and D[yn, xn] > 0:
        return float(D[yn, xn])
    return None


def slow_reference(depth, normal, pixels, K_train, K_full, grey_ref, sources, patch, min_std, max_fb, gamma=0.0,
                   best=0, max_cost=2.0):
    """Loop-per-pixel, per-source, per-patch-position PGSR consistency in numpy. Warps by
    explicit ray-plane intersection (not a homography). ``sources``: tuples
    ``(K_full, ref_to_src, grey, depth_train or None, K_train or None)``; ``gamma > 0``:
    NCC with adaptive support weights ``exp(-|a - a_centre| / gamma)``; ``best > 0``: only
    each pixel's ``best`` valid pairs of lowest cost count (the first source on ties);
    ``max_cost``: pairs of higher cost are invalid.
    Returns ``(photo, geo, valid_fraction, n_valid, n_geo)``."""
    h, w = depth.shape
    H, W = grey_ref.shape
    sx, sy = W / w, H / h
    r = patch // 2
    photo = geo = 0.0
    n_valid = n_geo = 0
    for x, y in pixels:
        z = depth[y, x]
        n = normal[y, x] / np.linalg.norm(normal[y, x])
        X = z * np.linalg.solve(K_train, [x, y, 1.0])
        rho = n @ X
        cx, cy = sx * (x + 0.5) - 0.5, sy * (y + 0.5) - 0.5
        pts = [(cx + dx, cy + dy) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
        ref_in = all(0 <= u <= W - 1 and 0 <= v <= H - 1 for u, v in pts)
        a = np.array([bilinear_np(grey_ref, u, v) for u, v in pts]) if ref_in else None
        wts = np.full(len(pts), 1.0 / len(pts))
        if ref_in and gamma > 0:
            wts = np.exp(-np.abs(a - a[len(pts) // 2]) / gamma)
            wts /= wts.sum()
        ma = wts @ a if ref_in else 0.0
        var_a = wts @ (a - ma) ** 2 if ref_in else 0.0
        if not (z > MIN_Z and abs(rho) > MIN_Z and ref_in and math.sqrt(var_a) >= min_std):
            continue
        pairs = []  # (cost, weight, phi or None) of this pixel's valid pairs, in source order
        for Ks_full, T, grey, D, Ks in sources:
            R, t = T[:3, :3], T[:3, 3]
            Xs = R @ X + t
            if Xs[2] <= MIN_Z:
                continue
            Hs, Ws = grey.shape
            b = []
            for u, v in pts:
                ray = np.linalg.solve(K_full, [u, v, 1.0])  # z = 1
                lam = rho / (n @ ray)  # reference depth of the plane point on this ray
                Ps = R @ (lam * ray) + t
                if not Ps[2] / lam > MIN_Z:  # homogeneous coordinate of the warp
                    break
                us, vs = (Ks_full @ Ps)[:2] / Ps[2]
                if not (0 <= us <= Ws - 1 and 0 <= vs <= Hs - 1):
                    break
                b.append(bilinear_np(grey, us, vs))
            if len(b) < len(pts):
                continue
            b = np.array(b)
            mb = wts @ b
            ncc = (wts @ ((a - ma) * (b - mb))) / np.sqrt(var_a * (wts @ (b - mb) ** 2) + 1e-8)
            cost = min(max(1.0 - ncc, 0.0), 2.0)
            weight, phi = 1.0, None
            if D is not None:
                px, py = (Ks @ Xs)[:2] / Xs[2]
                d = depth_lookup_np(D, px, py)
                if d is None:
                    continue
                Y = R.T @ (d * np.linalg.solve(Ks, [px, py, 1.0]) - t)
                q = K_train @ Y
                if q[2] <= MIN_Z:
                    continue
                phi = math.hypot(q[0] / q[2] - x, q[1] / q[2] - y)
                if phi >= max_fb:
                    continue
                weight = math.exp(-phi)
            if cost <= max_cost:
                pairs.append((cost, weight, phi))
        if best > 0:
            pairs = sorted(pairs, key=lambda c: c[0])[:best]  # sorted() is stable: source order on ties
        for cost, weight, phi in pairs:
            if phi is not None:
                geo += phi
                n_geo += 1
            photo += weight * cost
            n_valid += 1
    return (photo / max(n_valid, 1), geo / max(n_geo, 1), n_valid / (len(pixels) * len(sources)), n_valid, n_geo)


# ------------------------------------------------------------------- random problems
def smooth_image(rng, H: int, W: int, k: int = 4) -> np.ndarray:
    """Sum of ``k`` random sinusoids at the pixel centres, in [0.1, 0.9]."""
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    img = np.full((H, W), 0.5)
    for _ in range(k):
        f = rng.uniform(0.3, 1.2, 2) * rng.choice([-1, 1], 2)
        img += 0.4 / k * np.sin(f[0] * u + f[1] * v + rng.uniform(0, 2 * np.pi))
    return img


def random_problem(seed: int, h: int = 8, w: int = 10, s: int = 2, noise_image: bool = True,
                   depth_noise: float = 0.01, src_depth_noise: float = 0.02, zero_frac: float = 0.1):
    """A near-planar reference depth (plane at ~5 units, per-pixel noise), noisy
    non-unit normals, two source cameras orbiting the plane's centre (the first with a
    noisy rendered depth that has holes), random or smooth images. Numpy float64."""
    rng = np.random.default_rng(seed)
    H, W = s * h, s * w
    f = 1.6 * w
    K_train = np.array([[f * rng.uniform(0.95, 1.05), 0, (w - 1) / 2 + rng.uniform(-0.5, 0.5)],
                        [0, f * rng.uniform(0.95, 1.05), (h - 1) / 2 + rng.uniform(-0.5, 0.5)], [0, 0, 1.0]])
    K_full = scale_K(K_train, s)
    n0 = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), -1.0])
    n0 /= np.linalg.norm(n0)
    P0 = np.array([0.0, 0.0, 5.0])
    rho0 = n0 @ P0
    depth = plane_depth(K_train, np.eye(4), n0, rho0, h, w) * (1 + depth_noise * rng.standard_normal((h, w)))
    normal = (n0 + 0.15 * rng.standard_normal((h, w, 3))) * rng.uniform(0.5, 2.0, (h, w, 1))
    image = (lambda HH, WW: rng.uniform(0, 1, (HH, WW))) if noise_image else (lambda HH, WW: smooth_image(rng, HH, WW))
    grey_ref = image(H, W)
    sources = []
    for i, (axis, deg) in enumerate((((0.1, 1, 0.2), 9.0), ((1, 0.3, 0), -8.0))):
        T = orbit(P0, axis, deg)
        Hs, Ws = H + 2 * i, W - 2 * i  # a different source size
        Ks_full = K_full + np.array([[0, 0, -i], [0, 0, i], [0, 0, 0.0]])
        grey = image(Hs, Ws)
        D = Ks = None
        if i == 0:
            hs, ws = h + 1, w - 1
            Ks = np.array([[f, 0, (ws - 1) / 2], [0, f, (hs - 1) / 2], [0, 0, 1.0]])
            D = plane_depth(Ks, T, n0, rho0, hs, ws) * (1 + src_depth_noise * rng.standard_normal((hs, ws)))
            D[rng.uniform(size=D.shape) < zero_frac] = 0.0
        sources.append((Ks_full, T, grey, D, Ks))
    return {"depth": depth, "normal": normal, "K_train": K_train, "K_full": K_full, "grey_ref": grey_ref,
            "sources": sources}


def to_torch(p, pixels, **kw):
    """Arguments of multiview_consistency (float64 torch) from a random_problem dict."""
    srcs = [SourceView(t64(Kf), t64(T), t64(g), None if D is None else t64(D), None if Ks is None else t64(Ks))
            for Kf, T, g, D, Ks in p["sources"]]
    return dict(depth=kw.pop("depth", t64(p["depth"])), normal=kw.pop("normal", t64(p["normal"])), pixels=pixels,
                K_train=t64(p["K_train"]), K_full=t64(p["K_full"]), grey_ref_full=t64(p["grey_ref"]),
                sources=srcs, **kw)


# ------------------------------------------------------------------------ 1. homographies
def test_plane_homographies_match_ray_plane_intersection():
    rng = np.random.default_rng(3)
    M = 20
    K_ref = np.array([[300.0, 0.5, 161.2], [0, 290.0, 118.7], [0, 0, 1]])
    K_src = np.array([[280.0, 0, 150.3], [0, 285.0, 125.9], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = rot(rng.normal(size=3), 14.0)
    T[:3, 3] = rng.normal(size=3)
    normals = rng.normal(size=(M, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    points = rng.uniform(-1, 1, (M, 3)) + [0, 0, 8.0]
    Hm = plane_homographies(t64(K_ref), t64(K_src), t64(T), t64(normals), t64(points)).numpy()
    assert Hm.shape == (M, 3, 3)
    for m in range(M):
        n, rho = normals[m], normals[m] @ points[m]
        for q in ([0.0, 0.0, 1.0], [319.0, 239.0, 1.0], [rng.uniform(0, 320), rng.uniform(0, 240), 1.0]):
            ray = np.linalg.solve(K_ref, q)
            X = rho / (n @ ray) * ray
            assert abs(n @ X - rho) < 1e-9
            p = K_src @ (T[:3, :3] @ X + T[:3, 3])
            h = Hm[m] @ q
            np.testing.assert_allclose(h[:2] / h[2], p[:2] / p[2], rtol=0, atol=1e-9)
    # Invariant to the normal's scale (n / rho).
    H2 = plane_homographies(t64(K_ref), t64(K_src), t64(T), t64(3.0 * normals), t64(points)).numpy()
    np.testing.assert_allclose(H2, Hm, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------ 2. slow reference
@pytest.mark.parametrize("kernel", ["fused", "torch"])
@pytest.mark.parametrize("seed,patch,max_fb,gamma", [(0, 3, 0.05, 0.0), (1, 5, 0.2, 0.0), (2, 3, 1.0, 0.0),
                                                    (0, 3, 0.2, 0.05), (1, 5, 1.0, 0.1)])
def test_matches_slow_reference(seed, patch, max_fb, gamma, kernel):
    p = random_problem(seed)
    h, w = p["depth"].shape
    p["grey_ref"][: 2 * h // 2, : 2 * w // 3] = 0.4  # a textureless block: excluded pairs
    pixels = all_pixels(h, w)
    out = multiview_consistency(**to_torch(p, pixels, patch=patch, max_fb_px=max_fb, ncc_gamma=gamma, kernel=kernel))
    photo, geo, frac, n_valid, n_geo = slow_reference(
        p["depth"], p["normal"], pixels.tolist(), p["K_train"], p["K_full"], p["grey_ref"], p["sources"],
        patch, 0.01, max_fb, gamma)
    # Non-trivial: valid and invalid pairs, and some with the forward-backward check.
    assert 5 <= n_valid < 0.9 * len(pixels) * 2 and n_geo >= 3
    assert out["valid_fraction"].item() == pytest.approx(frac, abs=1e-12)
    assert out["photo"].item() == pytest.approx(photo, abs=1e-10)
    assert out["geo"].item() == pytest.approx(geo, abs=1e-10)


@pytest.mark.parametrize("best,max_cost", [(1, 2.0), (2, 2.0), (0, 0.6), (1, 0.8)])
def test_source_selection_matches_slow_reference(best, max_cost):
    """Only each pixel's lowest-cost pairs (``best_sources``) and pairs below ``max_cost``
    count, in both terms; with two sources ``best_sources`` 2 is every source."""
    p = random_problem(3)
    h, w = p["depth"].shape
    pixels = all_pixels(h, w)
    out = multiview_consistency(**to_torch(p, pixels, patch=3, max_fb_px=1.0, best_sources=best, max_cost=max_cost))
    photo, geo, frac, n_valid, n_geo = slow_reference(
        p["depth"], p["normal"], pixels.tolist(), p["K_train"], p["K_full"], p["grey_ref"], p["sources"],
        3, 0.01, 1.0, 0.0, best=best, max_cost=max_cost)
    _, _, _, n_all, _ = slow_reference(p["depth"], p["normal"], pixels.tolist(), p["K_train"], p["K_full"],
                                       p["grey_ref"], p["sources"], 3, 0.01, 1.0)
    # Non-trivial: the selection drops pairs (except best 2 of 2 sources) and keeps some.
    assert 5 <= n_valid and n_geo >= 3 and (n_valid < n_all) == (best == 1 or max_cost < 2.0)
    assert out["valid_fraction"].item() == pytest.approx(frac, abs=1e-12)
    assert out["photo"].item() == pytest.approx(photo, abs=1e-10)
    assert out["geo"].item() == pytest.approx(geo, abs=1e-10)


def test_source_selection_gradcheck():
    p = random_problem(5, h=5, w=6, noise_image=False, depth_noise=0.003, src_depth_noise=0.01, zero_frac=0.0)
    pixels = torch.tensor([[2, 2], [3, 2], [3, 3], [2, 1]])
    args = to_torch(p, pixels, patch=3, max_fb_px=2.0, best_sources=1)
    args["sources"] = [SourceView(s.K_full, s.ref_to_src, s.grey_full) for s in args["sources"]]
    depth = args.pop("depth").requires_grad_()
    normal = args.pop("normal").requires_grad_()
    assert multiview_consistency(depth, normal, **args)["photo"] > 1e-3
    assert torch.autograd.gradcheck(lambda d, n: multiview_consistency(d, n, **args)["photo"], (depth, normal),
                                    eps=1e-6, atol=1e-6, rtol=1e-4)


def test_float32_close_to_float64():
    p = random_problem(0)
    args = to_torch(p, all_pixels(*p["depth"].shape), max_fb_px=1.0)
    o64 = multiview_consistency(**args)
    args32 = dict(args, depth=args["depth"].float(), normal=args["normal"].float(), K_train=args["K_train"].float(),
                  K_full=args["K_full"].float(), grey_ref_full=args["grey_ref_full"].float(),
                  sources=[SourceView(s.K_full.float(), s.ref_to_src.float(), s.grey_full.float(),
                                      None if s.depth_train is None else s.depth_train.float(),
                                      None if s.K_train is None else s.K_train.float()) for s in args["sources"]])
    o32 = multiview_consistency(**args32)
    assert o32["photo"].dtype == torch.float32
    assert o32["valid_fraction"].item() == pytest.approx(o64["valid_fraction"].item())
    assert o32["photo"].item() == pytest.approx(o64["photo"].item(), abs=1e-4)
    assert o32["geo"].item() == pytest.approx(o64["geo"].item(), abs=1e-4)


@pytest.mark.parametrize("dtype,gamma", [(torch.float64, 0.0), (torch.float64, 0.05), (torch.float32, 0.0),
                                         (torch.float32, 0.05)])
def test_fused_kernels_match_the_torch_composition(dtype, gamma):
    """The numba kernels (``kernel='fused'``) against their torch reference on a larger
    problem: the same valid pairs, terms and gradients (float rounding apart)."""
    p = random_problem(7, h=24, w=32, s=2, noise_image=False)
    args = to_torch(p, all_pixels(24, 32), patch=7, max_fb_px=1.0, ncc_gamma=gamma)
    cast = (lambda x: x.to(dtype) if torch.is_tensor(x) else x)  # noqa: E731
    args = {k: cast(v) for k, v in args.items()}
    args["pixels"] = all_pixels(24, 32)
    args["sources"] = [SourceView(*(None if x is None else x.to(dtype) for x in
                                    (s.K_full, s.ref_to_src, s.grey_full, s.depth_train, s.K_train)))
                       for s in args["sources"]]
    outs, grads = [], []
    for kernel in ("fused", "torch"):
        depth = args["depth"].clone().requires_grad_()
        normal = args["normal"].clone().requires_grad_()
        out = multiview_consistency(depth, normal, **{k: v for k, v in args.items() if k not in ("depth", "normal")},
                                    kernel=kernel)
        outs.append(out)
        grads.append(torch.autograd.grad(out["photo"] + out["geo"], (depth, normal)))
    (f, t), ((fd, fn), (td, tn)) = outs, grads
    assert 0.3 < t["valid_fraction"].item() < 1.0  # valid and invalid pairs
    assert f["valid_fraction"].item() == t["valid_fraction"].item()
    tol = 1e-10 if dtype == torch.float64 else 2e-5
    assert f["photo"].item() == pytest.approx(t["photo"].item(), rel=tol, abs=tol)
    assert f["geo"].item() == pytest.approx(t["geo"].item(), rel=tol, abs=tol)
    for a, b in ((fd, td), (fn, tn)):
        assert b.abs().max() > 0
        torch.testing.assert_close(a, b, rtol=tol * 50, atol=tol * float(b.abs().max()) * 50)


def test_fused_kernel_refuses_other_devices_and_names():
    p = random_problem(0)
    with pytest.raises(ValueError, match="kernel must be one of"):
        multiview_consistency(**to_torch(p, all_pixels(*p["depth"].shape), kernel="numba"))


# --------------------------------------------------------------------------- 3. gradcheck
@pytest.mark.parametrize("kernel", ["fused", "torch"])
def test_gradcheck_photo_and_geo(kernel):
    """Photo: sources without depth (weight 1; with depth the weight exp(-phi) is detached on
    purpose, so finite differences would see a dependence autograd does not). Geo: the
    source with a rendered depth."""
    p = random_problem(5, h=5, w=6, noise_image=False, depth_noise=0.003, src_depth_noise=0.01, zero_frac=0.0)
    pixels = torch.tensor([[2, 2], [3, 2], [3, 3], [2, 1]])
    args = to_torch(p, pixels, patch=3, max_fb_px=2.0, kernel=kernel)
    depth = args.pop("depth").requires_grad_()
    normal = args.pop("normal").requires_grad_()
    out = multiview_consistency(depth, normal, **args)
    assert out["valid_fraction"] >= 0.5 and out["photo"] > 1e-3 and out["geo"] > 1e-4
    photo_args = dict(args, sources=[SourceView(s.K_full, s.ref_to_src, s.grey_full) for s in args["sources"]])
    geo_args = dict(args, sources=args["sources"][:1])
    assert multiview_consistency(depth, normal, **photo_args)["valid_fraction"] >= 0.5

    def f(d, n):
        return multiview_consistency(d, n, **photo_args)["photo"], multiview_consistency(d, n, **geo_args)["geo"]

    assert torch.autograd.gradcheck(f, (depth, normal), eps=1e-6, atol=1e-6, rtol=1e-4)
    g_d, g_n = torch.autograd.grad(out["photo"] + out["geo"], (depth, normal))
    assert g_d.abs().sum() > 0 and g_n.abs().sum() > 0

    def f_weighted(d, n):
        return multiview_consistency(d, n, **photo_args, ncc_gamma=0.05)["photo"]

    assert multiview_consistency(depth, normal, **photo_args, ncc_gamma=0.05)["photo"] > 1e-3
    assert torch.autograd.gradcheck(f_weighted, (depth, normal), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_adaptive_support_weights_limit_and_effect():
    """A very large ``ncc_gamma`` gives (numerically) uniform weights: plain NCC; a small one
    changes the cost, in both L_mv and best_source_ncc."""
    p = random_problem(1)
    pixels = all_pixels(*p["depth"].shape)
    plain = multiview_consistency(**to_torch(p, pixels, patch=5))
    wide = multiview_consistency(**to_torch(p, pixels, patch=5, ncc_gamma=1e9))
    sharp = multiview_consistency(**to_torch(p, pixels, patch=5, ncc_gamma=0.02))
    assert wide["photo"].item() == pytest.approx(plain["photo"].item(), abs=1e-9)
    assert abs(sharp["photo"].item() - plain["photo"].item()) > 1e-3
    args = to_torch(p, pixels, patch=5)
    args.pop("max_fb_px", None)
    b_plain = best_source_ncc(**args)
    b_wide = best_source_ncc(**args, ncc_gamma=1e9)
    b_sharp = best_source_ncc(**args, ncc_gamma=0.02)
    both = ~torch.isnan(b_plain)
    assert both.sum() >= 5 and torch.equal(both, ~torch.isnan(b_wide))
    assert torch.allclose(b_wide[both], b_plain[both], atol=1e-9)
    # Sharp weights also make some patches flat (weighted std below min_patch_std): nan there.
    sharp_ok = both & ~torch.isnan(b_sharp)
    assert sharp_ok.sum() >= 5 and (b_sharp[sharp_ok] - b_plain[sharp_ok]).abs().max() > 1e-3


# --------------------------------------------------------- 4. minimum at the true plane
class PlaneScene:
    """A textured plane seen by a reference and two sources ~10 degrees apart, images
    rendered at 160x120 by exact ray-plane intersection; training resolution 80x60."""

    W, H, w, h = 160, 120, 80, 60

    def __init__(self):
        rng = np.random.default_rng(7)
        self.K_train = np.array([[100.0, 0, 39.5], [0, 100.0, 29.5], [0, 0, 1]])
        self.K_full = scale_K(self.K_train, 2)  # f = 200: one full-res pixel ~ 0.5 (units) at 100
        self.P0 = np.array([0.0, 0.0, 100.0])
        self.n = rot((1, 0, 0), 12) @ rot((0, 1, 0), -18) @ np.array([0, 0, -1.0])
        self.rho = float(self.n @ self.P0)
        e1 = np.cross(self.n, [0, 1.0, 0])
        self.e1 = e1 / np.linalg.norm(e1)
        self.e2 = np.cross(self.n, self.e1)
        # 10 sinusoids with periods of 4-10 full-res pixels (2-5 units on the plane).
        period = rng.uniform(2.0, 5.0, 10)
        ang = rng.uniform(0, np.pi, 10)
        self.freq = np.stack([np.cos(ang), np.sin(ang)], -1) * (2 * np.pi / period)[:, None]
        self.phase = rng.uniform(0, 2 * np.pi, 10)
        self.T_src = [orbit(self.P0, (0, 1, 0), 10.0), orbit(self.P0, (1, 0, 0), -10.0)]
        self.grey_ref = self.render(self.K_full, np.eye(4), self.H, self.W)
        self.grey_src = [self.render(self.K_full, T, self.H, self.W) for T in self.T_src]
        self.depth = plane_depth(self.K_train, np.eye(4), self.n, self.rho, self.h, self.w)
        self.depth_src = [plane_depth(self.K_train, T, self.n, self.rho, self.h, self.w) for T in self.T_src]

    def render(self, K, T, H, W):
        R, t = T[:3, :3], T[:3, 3]
        c = -R.T @ t
        u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
        d = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(K).T @ R  # rays, reference frame
        lam = (self.rho - self.n @ c) / (d @ self.n)
        P = c + lam[..., None] * d - self.P0
        ab = np.stack([P @ self.e1, P @ self.e2], -1)
        return 0.5 + 0.04 * np.sin(ab @ self.freq.T + self.phase).sum(-1)

    def sources(self, with_depth: bool, depth_src=None):
        depth_src = self.depth_src if depth_src is None else depth_src
        return [SourceView(t64(self.K_full), t64(T), t64(g), t64(D) if with_depth else None,
                           t64(self.K_train) if with_depth else None)
                for T, g, D in zip(self.T_src, self.grey_src, depth_src)]

    def loss(self, depth=None, normal=None, pixels=None, with_depth=False, depth_src=None, **kw):
        depth = self.depth if depth is None else depth
        normal = np.broadcast_to(self.n, (self.h, self.w, 3)) if normal is None else normal
        pixels = all_pixels(self.h, self.w) if pixels is None else pixels
        return multiview_consistency(t64(depth), t64(normal.copy()), pixels, t64(self.K_train), t64(self.K_full),
                                     t64(self.grey_ref), self.sources(with_depth, depth_src), **kw)


@pytest.fixture(scope="module")
def scene():
    return PlaneScene()


def test_true_plane_is_the_minimum(scene):
    dist = abs(scene.rho)
    truth = scene.loss(with_depth=True)
    assert truth["valid_fraction"] > 0.7
    assert truth["photo"] < 0.01 and truth["geo"] < 0.02

    def photo_depth(delta):  # depth offset by delta * (plane distance), photometric only
        return scene.loss(depth=scene.depth + delta * dist)["photo"].item()

    def photo_tilt(axis, deg):
        n = rot(axis, deg) @ scene.n
        return scene.loss(normal=np.broadcast_to(n, (scene.h, scene.w, 3)))["photo"].item()

    p0 = photo_depth(0.0)
    for sign in (1, -1):
        assert p0 < photo_depth(sign * 0.01) < photo_depth(sign * 0.02)
        for axis in ((1, 0, 0), (0, 1, 0)):
            assert p0 < photo_tilt(axis, sign * 5) < photo_tilt(axis, sign * 10)
    step = 0.005
    sweep = [photo_depth(k * step) for k in range(-6, 7)]
    assert abs(int(np.argmin(sweep)) - 6) <= 1
    # The geometric term grows with the depth error too (the sources' depths are exact).
    assert truth["geo"] < scene.loss(depth=scene.depth * 1.01, with_depth=True)["geo"] < 1.0


def test_best_source_keeps_the_source_that_sees_the_point(scene):
    """One source shows something else where the plane is (an occluder's texture, within the
    forward-backward tolerance): with every source the cost at the true plane is high; with
    each pixel's best source it is as low as with the seeing source alone, and the true plane
    is still the minimum along the depth."""
    occluded = copy.copy(scene)
    occluded.grey_src = [scene.grey_src[0], np.random.default_rng(11).uniform(0.3, 0.7, scene.grey_src[1].shape)]
    every = occluded.loss()["photo"].item()
    best = occluded.loss(best_sources=1)["photo"].item()
    assert best < 0.05 and every > 10 * best
    step = 0.005 * abs(scene.rho)
    sweep = [occluded.loss(depth=scene.depth + k * step, best_sources=1)["photo"].item() for k in range(-4, 5)]
    assert int(np.argmin(sweep)) == 4 and sweep[0] > 5 * best and sweep[-1] > 5 * best


# ------------------------------------------------------------------------ 5. bad input
def _args():
    p = random_problem(0, h=6, w=7)
    return to_torch(p, all_pixels(6, 7))


@pytest.mark.parametrize("change,name", [
    (lambda a: a.update(depth=a["depth"][None]), "depth"),
    (lambda a: a.update(normal=a["normal"][..., :2]), "normal"),
    (lambda a: a.update(pixels=torch.zeros(4, 3, dtype=torch.long)), "pixels"),
    (lambda a: a.update(pixels=a["pixels"].double()), "pixels"),
    (lambda a: a.update(pixels=torch.tensor([[7, 0]])), "pixels"),
    (lambda a: a.update(pixels=torch.tensor([[0, 6]])), "pixels"),
    (lambda a: a.update(pixels=torch.tensor([[-1, 0]])), "pixels"),
    (lambda a: a.update(patch=4), "patch"),
    (lambda a: a.update(patch=0), "patch"),
    (lambda a: a.update(ncc_gamma=-0.1), "ncc_gamma"),
    (lambda a: a.update(ncc_gamma=float("nan")), "ncc_gamma"),
    (lambda a: a.update(ncc_gamma=float("inf")), "ncc_gamma"),
    (lambda a: a.update(K_train=a["K_train"][:2]), "K_train"),
    (lambda a: a.update(K_full=a["K_full"] * 1.01), "K_full"),
    (lambda a: a.update(grey_ref_full=a["grey_ref_full"][None]), "grey_ref_full"),
    (lambda a: setattr(a["sources"][1], "ref_to_src", a["sources"][1].ref_to_src[:3]), "ref_to_src"),
    (lambda a: setattr(a["sources"][0], "K_train", None), "K_train"),
])
def test_bad_input_raises(change, name):
    a = _args()
    change(a)
    with pytest.raises(ValueError, match=name):
        multiview_consistency(**a)


def test_plane_homographies_bad_input():
    K, T = torch.eye(3, dtype=torch.float64), torch.eye(4, dtype=torch.float64)
    with pytest.raises(ValueError, match="normals"):
        plane_homographies(K, K, T, torch.ones(4, 2, dtype=torch.float64), torch.ones(4, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match="points"):
        plane_homographies(K, K, T, torch.ones(4, 3, dtype=torch.float64), torch.ones(5, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="ref_to_src"):
        plane_homographies(K, K, T[:3], torch.ones(4, 3, dtype=torch.float64), torch.ones(4, 3, dtype=torch.float64))


def _behind(a):  # sources at the reference centre, turned around: every point behind them
    T = np.eye(4)
    T[:3, :3] = rot((0, 1, 0), 180.0)
    for s in a["sources"]:
        s.ref_to_src = t64(T)


def _no_source_depth(a):
    a["sources"][0].depth_train = torch.zeros_like(a["sources"][0].depth_train)
    a["sources"].pop(1)


@pytest.mark.parametrize("change", [
    _behind,
    _no_source_depth,
    lambda a: a.update(pixels=torch.tensor([[0, 0], [6, 5], [0, 3]])),  # patches leave the image
    lambda a: a.update(pixels=torch.zeros(0, 2, dtype=torch.long)),
    lambda a: a.update(sources=[]),
    lambda a: a.update(depth=torch.zeros_like(a["depth"])),
    lambda a: a.update(grey_ref_full=torch.full_like(a["grey_ref_full"], 0.3)),  # flat: textureless
])
def test_no_valid_pair_gives_zeros_with_zero_gradients(change):
    a = _args()
    change(a)
    a["depth"].requires_grad_()
    a["normal"].requires_grad_()
    out = multiview_consistency(**a)
    assert out["valid_fraction"].item() == 0.0
    assert out["photo"].item() == 0.0 and out["geo"].item() == 0.0
    g_d, g_n = torch.autograd.grad(out["photo"] + out["geo"], (a["depth"], a["normal"]))
    assert torch.equal(g_d, torch.zeros_like(g_d)) and torch.equal(g_n, torch.zeros_like(g_n))


# ------------------------------------------------------------------ 6. forward-backward
def test_forward_backward_occlusion(scene):
    truth = scene.loss(with_depth=True)
    assert truth["valid_fraction"] > 0.7 and truth["geo"] < 0.02
    # Source 0 only; its depth map with a much nearer occluder over its left half.
    T = scene.T_src[0]
    u, v = np.meshgrid(np.arange(scene.w, dtype=float), np.arange(scene.h, dtype=float))
    X = scene.depth[..., None] * (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(scene.K_train).T)
    Xs = X @ T[:3, :3].T + T[:3, 3]
    xs = (Xs @ scene.K_train.T)[..., 0] / Xs[..., 2]  # column in source 0's training depth
    occluded = scene.depth_src[0].copy()
    occluded[:, : scene.w // 2] *= 0.8
    pix = all_pixels(scene.h, scene.w)
    left = torch.from_numpy(xs.reshape(-1) < scene.w // 2 - 2)
    right = torch.from_numpy(xs.reshape(-1) > scene.w // 2 + 1)

    def run(pixels, depth_src):
        sources = scene.sources(True, depth_src)[:1]
        return multiview_consistency(t64(scene.depth), t64(np.broadcast_to(scene.n, (scene.h, scene.w, 3)).copy()),
                                     pixels, t64(scene.K_train), t64(scene.K_full), t64(scene.grey_ref), sources)

    for side in (left, right):
        clear = run(pix[side], None)
        assert clear["valid_fraction"] > 0.6 and clear["geo"] < 0.02
    assert run(pix[left], [occluded])["valid_fraction"] == 0.0  # occluded: all invalid
    unocc = run(pix[right], [occluded])
    assert unocc["valid_fraction"].item() == pytest.approx(run(pix[right], None)["valid_fraction"].item())
    assert unocc["geo"] < 0.02


# ------------------------------------------------------------- best_source_ncc (pruning)
@pytest.mark.parametrize("kernel", ["fused", "torch"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_best_source_ncc_matches_slow_reference(seed, kernel):
    """Per pixel, the best over sources of 1 - the slow reference's cost of that single
    (pixel, source) pair without depth check (its cost is 1 - NCC there), nan where no pair
    is valid."""
    p = random_problem(seed, noise_image=seed != 1)
    pixels = all_pixels(*p["depth"].shape)
    args = to_torch(p, pixels, kernel=kernel)
    args["sources"] = [SourceView(s.K_full, s.ref_to_src, s.grey_full) for s in args["sources"]]
    got = best_source_ncc(**args, patch=3, min_patch_std=0.01).numpy()
    n_valid = 0
    for m, (x, y) in enumerate(pixels.tolist()):
        nccs = []
        for Kf, T, g, _, _ in p["sources"]:
            photo, _, _, nv, _ = slow_reference(p["depth"], p["normal"], [(x, y)], p["K_train"], p["K_full"],
                                                p["grey_ref"], [(Kf, T, g, None, None)], 3, 0.01, 1.0)
            if nv:
                nccs.append(1.0 - photo)
        if nccs:
            n_valid += 1
            assert got[m] == pytest.approx(max(nccs), abs=1e-9), (x, y)
        else:
            assert np.isnan(got[m]), (x, y)
    assert n_valid > 0.5 * len(pixels)


def test_best_source_ncc_is_high_on_the_true_plane_only(scene):
    def best(depth):
        return best_source_ncc(t64(depth), t64(np.broadcast_to(scene.n, (scene.h, scene.w, 3)).copy()),
                               all_pixels(scene.h, scene.w), t64(scene.K_train), t64(scene.K_full),
                               t64(scene.grey_ref), scene.sources(False)).numpy()

    truth = best(scene.depth)
    assert np.isfinite(truth).mean() > 0.7
    assert np.nanmedian(truth) > 0.99
    # Monotone in the depth error, and low once the parallax exceeds the texture's period.
    medians = [np.nanmedian(best(scene.depth * f)) for f in (1.01, 1.02, 1.05, 1.1)]
    assert np.nanmedian(truth) > medians[0] > medians[1] > medians[2] > medians[3]
    assert medians[3] < 0.4 and np.nanmedian(best(scene.depth * 0.9)) < 0.4


def test_best_source_ncc_flat_patch_is_no_evidence(scene):
    flat = torch.full((scene.H, scene.W), 0.5, dtype=torch.float64)
    got = best_source_ncc(t64(scene.depth), t64(np.broadcast_to(scene.n, (scene.h, scene.w, 3)).copy()),
                          all_pixels(scene.h, scene.w), t64(scene.K_train), t64(scene.K_full), flat,
                          scene.sources(False))
    assert torch.isnan(got).all()


def test_best_source_ncc_ignores_sources_that_do_not_see_the_point(scene):
    args = (t64(scene.depth), t64(np.broadcast_to(scene.n, (scene.h, scene.w, 3)).copy()), all_pixels(scene.h, scene.w),
            t64(scene.K_train), t64(scene.K_full), t64(scene.grey_ref))
    plain = best_source_ncc(*args, scene.sources(False)).numpy()
    seen = best_source_ncc(*args, scene.sources(True)).numpy()  # exact source depths: every source sees the plane
    both = np.isfinite(plain) & np.isfinite(seen)
    assert both.mean() > 0.6 and np.array_equal(plain[both], seen[both])
    occluded = best_source_ncc(*args, scene.sources(True, [0.9 * D for D in scene.depth_src])).numpy()
    assert np.isnan(occluded).all()  # something 10% nearer in every source: no evidence
    farther = best_source_ncc(*args, scene.sources(True, [1.1 * D for D in scene.depth_src])).numpy()
    assert np.array_equal(np.isnan(farther), np.isnan(seen) | ~np.isfinite(farther))
    assert np.isfinite(farther).mean() > 0.6  # a source seeing past the point still judges it


def _slow_reference_pixels(surface, normal, K, max_incidence_deg):
    """Pixel by pixel: on the surface, and the angle between the normal and the ray at most
    max_incidence_deg."""
    h, w = surface.shape
    Kinv = np.linalg.inv(K.numpy().astype(np.float64))
    keep = np.zeros((h, w), bool)
    for y in range(h):
        for x in range(w):
            if surface[y, x]:
                ray = Kinv @ np.array([x, y, 1.0])
                n = normal[y, x].numpy().astype(np.float64)
                cos = abs(n @ ray) / (np.linalg.norm(n) * np.linalg.norm(ray))
                keep[y, x] = math.degrees(math.acos(min(cos, 1.0))) <= max_incidence_deg + 1e-9
    return keep


@pytest.mark.parametrize("max_deg", [30.0, 60.0, 70.0, 89.0])
def test_reference_pixels_match_slow_reference(max_deg):
    g = torch.Generator().manual_seed(3)
    h, w = 30, 40
    surface = torch.rand(h, w, generator=g) > 0.2
    normal = torch.randn(h, w, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]], dtype=torch.float64)
    got = reference_pixels(surface, normal, K, max_deg)
    want = _slow_reference_pixels(surface, normal, K, max_deg)
    assert got.dtype == torch.bool and got.shape == (h, w)
    assert (got.numpy() == want).all()
    assert 0 < got.sum() < surface.sum() and not (got & ~surface).any()
    # Either sign of the normal, and its length, do not matter.
    assert torch.equal(reference_pixels(surface, -3.0 * normal, K, max_deg), got)


def test_reference_pixels_leave_out_a_zero_normal():
    """A pixel with no rendered normal (all three components 0) has no incidence angle: it is
    not a reference pixel at any angle below 90 degrees."""
    surface = torch.ones(4, 5, dtype=torch.bool)
    normal = torch.zeros(4, 5, 3)
    normal[..., 2] = -1.0
    normal[1, 2] = 0.0
    K = torch.tensor([[20.0, 0, 2], [0, 20.0, 1.5], [0, 0, 1]])
    kept = reference_pixels(surface, normal, K, 70.0)
    assert not kept[1, 2] and kept.sum() == 19


def test_reference_pixels_at_90_degrees_keep_the_surface():
    surface = torch.rand(10, 12, generator=torch.Generator().manual_seed(0)) > 0.5
    normal = torch.randn(10, 12, 3)
    K = torch.tensor([[20.0, 0, 6], [0, 20.0, 5], [0, 0, 1]])
    assert torch.equal(reference_pixels(surface, normal, K, 90.0), surface)


def test_reference_pixels_cut_a_sphere_rim_at_the_angle():
    """A sphere seen head-on: the kept pixels are the disc where the surface is seen within the
    angle, i.e. image radius <= R sin(angle) for a distant sphere (orthographic limit)."""
    h = w = 201
    f, dist, R = 1.0e5, 1.0e4, 1.0  # nearly orthographic: the sphere spans ~20 px radius
    K = torch.tensor([[f, 0, 100.0], [0, f, 100.0], [0, 0, 1]], dtype=torch.float64)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    px, py = (xs - 100) * dist / f, (ys - 100) * dist / f
    r2 = px ** 2 + py ** 2
    surface = r2 < R ** 2
    normal = torch.stack([px, py, -torch.sqrt((R ** 2 - r2).clamp_min(0))], -1)  # outward, towards the camera
    for deg in (40.0, 70.0):
        kept = reference_pixels(surface, normal, K, deg)
        radius = torch.sqrt(r2[kept]).max().item()
        assert abs(radius - R * math.sin(math.radians(deg))) < 2 * dist / f  # within two pixels


# ----------------------------------------------------------------------------- textured pixels
def _slow_textured(grey: np.ndarray, h: int, w: int, patch: int, min_std: float, gamma: float):
    """Loop reference of :func:`textured_pixels`: each training pixel's full-resolution patch
    (integer offsets around ``s (x + 0.5) - 0.5``), bilinear samples, inside the image, and its
    (support-weighted) grey std. Returns the mask and the std."""
    H, W = grey.shape
    sx, sy = W / w, H / h
    r = patch // 2
    keep = np.zeros((h, w), bool)
    std = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            cx, cy = sx * (x + 0.5) - 0.5, sy * (y + 0.5) - 0.5
            vals, inside = [], True
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    px, py = cx + dx, cy + dy
                    if not (0 <= px <= W - 1 and 0 <= py <= H - 1):
                        inside = False
                        px, py = min(max(px, 0), W - 1), min(max(py, 0), H - 1)
                    x0, y0 = min(int(math.floor(px)), W - 2), min(int(math.floor(py)), H - 2)
                    fx, fy = px - x0, py - y0
                    vals.append((1 - fx) * (1 - fy) * grey[y0, x0] + fx * (1 - fy) * grey[y0, x0 + 1]
                                + (1 - fx) * fy * grey[y0 + 1, x0] + fx * fy * grey[y0 + 1, x0 + 1])
            a = np.array(vals)
            wgt = np.exp(-np.abs(a - a[len(a) // 2]) / gamma) if gamma > 0 else np.ones_like(a)
            wgt = wgt / wgt.sum()
            mean = (wgt * a).sum()
            std[y, x] = math.sqrt((wgt * (a - mean) ** 2).sum())
            keep[y, x] = inside and std[y, x] >= min_std
    return keep, std


def _half_flat_image(H: int, W: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(5)
    grey = torch.rand(H, W, generator=g, dtype=torch.float64)
    grey[:, : W // 2] = 0.5  # flat left half
    grey[H // 4: H // 2, 4:12] += 0.01 * torch.rand(H // 2 - H // 4, 8, generator=g, dtype=torch.float64)  # texture too faint to count
    return grey


@pytest.mark.parametrize("kernel", ["fused", "torch"])
@pytest.mark.parametrize("gamma", [0.0, 0.05])
@pytest.mark.parametrize("scale", [1, 2])
def test_textured_pixels_match_slow_reference(gamma, scale, kernel):
    H, W = 36, 48
    h, w = H // scale, W // scale
    grey = _half_flat_image(H, W)
    got = textured_pixels(grey, h, w, 5, 0.01, gamma, dtype=torch.float64, kernel=kernel)
    want, std = _slow_textured(grey.numpy(), h, w, 5, 0.01, gamma)
    assert got.dtype == torch.bool and got.shape == (h, w)
    clear = np.abs(std - 0.01) > 1e-9  # no pixel on the threshold decides the comparison
    assert (got.numpy() == want)[clear].all()
    # Both kinds present: the flat half and the border are out, the textured half in.
    assert 0 < got.sum() < h * w and not got[:, : w // 2 - 3].any()
    # The chunking does not change the answer.
    assert torch.equal(textured_pixels(grey, h, w, 5, 0.01, gamma, dtype=torch.float64, chunk=7, kernel=kernel), got)


@pytest.mark.parametrize("gamma", [0.0, 0.05])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_textured_pixels_are_where_the_loss_can_have_a_pair(gamma, dtype):
    """No pixel outside the mask has a valid pair in multiview_consistency; pixels inside it
    do: sampling L_mv's points among the textured pixels drops only pairs that count for
    nothing."""
    p = random_problem(0, h=12, w=16)
    p["grey_ref"][:, : p["grey_ref"].shape[1] // 2] = 0.5  # a flat half: no NCC there
    h, w = p["depth"].shape
    args = to_torch(p, None, ncc_gamma=gamma, min_patch_std=0.01, patch=5)
    args = {k: (v.to(dtype) if torch.is_tensor(v) else v) for k, v in args.items()}
    args["sources"] = [SourceView(*(None if x is None else x.to(dtype) for x in
                                    (s.K_full, s.ref_to_src, s.grey_full, s.depth_train, s.K_train)))
                       for s in args["sources"]]
    tex = textured_pixels(args["grey_ref_full"], h, w, 5, 0.01, gamma, dtype=dtype)
    assert 0 < tex.sum() < h * w
    ys, xs = torch.nonzero(torch.ones(h, w, dtype=torch.bool), as_tuple=True)
    for keep, has_pairs in ((tex, True), (~tex, False)):
        pix = torch.stack([xs[keep.reshape(-1)], ys[keep.reshape(-1)]], 1)
        out = multiview_consistency(**dict(args, pixels=pix))
        assert (out["valid_fraction"] > 0) == has_pairs


@pytest.mark.parametrize("gamma", [0.0, 0.05])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_patch_moments_kernel_matches_the_torch_composition(gamma, dtype):
    """The reference patches from the numba kernel against their torch composition, patches
    across the image's border (clamped samples) included, at a downscale of 2.5 and 1."""
    grey = _half_flat_image(30, 40).to(dtype)
    for h, w in ((12, 16), (30, 40)):
        ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).to(dtype)
        fused = _patch_moments(grey, pix, 40 / w, 30 / h, 5, gamma, "fused")
        ref = _patch_moments(grey, pix, 40 / w, 30 / h, 5, gamma, "torch")
        assert 0 < int(ref[1].sum()) < h * w  # patches inside and across the border
        tol = 1e-12 if dtype == torch.float64 else 1e-5  # float32: the kernel's sums run in float64
        for a, b in zip(fused, ref):
            if b is None:
                assert a is None
            elif b.dtype == torch.bool:
                assert torch.equal(a, b)
            else:
                assert a.dtype == dtype
                torch.testing.assert_close(a, b, rtol=tol, atol=tol)


def test_textured_pixels_bad_input():
    with pytest.raises(ValueError, match="grey_ref_full"):
        textured_pixels(torch.rand(3, 4, 5), 2, 2, 3, 0.01, 0.0)
    with pytest.raises(ValueError, match="patch"):
        textured_pixels(torch.rand(8, 8), 4, 4, 4, 0.01, 0.0)
