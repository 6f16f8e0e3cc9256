"""Parts of the optimize library: surfel initialisation and PLY layout, optimizer-consistent
edits, the densification strategy, the rendering losses (against slow references, with
gradients checked)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from pipeline.config.optimize import DensifyConfig
from pipeline.errors import ConfigError
from pipeline.losses import (
    depth_normal_loss,
    depth_to_normals,
    flat_pixels,
    mask_loss,
    mvs_depth_loss,
    normal_smoothness_loss,
    ssim,
)
from pipeline.optimize import ops
from pipeline.optimize.photoreset import visible_surfels_at
from pipeline.optimize.strategy import DensifyStrategy, screen_grad_ndc
from pipeline.optimize.seed import frames_from_normals, init_params, knn_scales
from pipeline.surfels import SurfelInitError, ply_attribute_names, read_surfel_ply, write_surfel_ply
from pipeline.geometry import rotmat_to_quat
from pipeline.rasterizer.project import quat_to_rotmat


def _params(n=50, seed=0, sh_degree=1):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(n, 3)) * 0.3
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return init_params(pts, nrm, rng.random((n, 3)), sh_degree, 0.1, rng, dtype=torch.float64), pts, nrm


def test_normals_become_the_third_rotation_column():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[:3] = [[0, 0, 1], [0, 0, -1], [1, 0, 0]]  # axis-aligned and antipodal cases
    R = frames_from_normals(n)
    assert np.allclose(np.einsum("nij,nik->njk", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    q = rotmat_to_quat(R)
    R2 = quat_to_rotmat(torch.from_numpy(q)).numpy()
    assert np.allclose(R2, R, atol=1e-12)
    assert np.allclose(R2[:, :, 2], n, atol=1e-12)


def test_init_scales_colours_and_opacity():
    params, pts, _ = _params()
    d = np.sort(np.linalg.norm(pts[:, None] - pts[None], axis=2), axis=1)[:, 1:4]
    expect = np.sqrt((d * d).mean(axis=1))
    assert np.allclose(torch.exp(params.log_scales).detach().numpy(), expect[:, None], rtol=1e-9)
    assert np.allclose(torch.sigmoid(params.opacity_logits).detach().numpy(), 0.1)
    colors = params.surfels(0).features[:, 0] * 0.28209479177387814 + 0.5
    assert torch.all((colors >= 0) & (colors <= 1))
    assert knn_scales(np.zeros((4, 3))).min() > 0  # coincident points: finite log-scale


def test_init_rejects_empty_and_non_finite_clouds():
    rng = np.random.default_rng(0)
    with pytest.raises(SurfelInitError, match="cloud.ply: no point"):
        init_params(np.zeros((0, 3)), None, np.zeros((0, 3)), 0, 0.1, rng, where="cloud.ply")
    with pytest.raises(SurfelInitError, match="non-finite"):
        init_params(np.array([[np.nan, 0, 0]]), None, np.zeros((1, 3)), 0, 0.1, rng)
    one = init_params(np.array([[0.1, 0.2, 0.3]]), None, np.full((1, 3), 0.5), 0, 0.1, rng)
    assert one.num == 1 and torch.isfinite(one.log_scales).all()


def test_ply_has_2dgs_layout_and_round_trips(tmp_path):
    params, _, _ = _params(sh_degree=2)
    S = np.diag([250.0, 250.0, 250.0, 1.0])
    S[:3, 3] = [10.0, -20.0, 600.0]
    path = write_surfel_ply(tmp_path / "s.ply", params, S)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    names = [ln.split()[-1] for ln in header.splitlines() if ln.startswith("property")]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-7:] == ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == ply_attribute_names(8) and sum(n.startswith("f_rest_") for n in names) == 24
    back = read_surfel_ply(path, S, dtype=torch.float64)
    for k, v in params.tensors().items():
        a, b = v.detach(), getattr(back, k).detach()
        if k == "quats":
            a = torch.nn.functional.normalize(a, dim=1)
        assert torch.allclose(a, b, atol=2e-5, rtol=1e-5), k
    # World-frame values: centres in mm, scales in mm.
    data = np.frombuffer(path.read_bytes().split(b"end_header\n")[1], "<f4").reshape(params.num, -1)
    assert np.allclose(data[:, :3], params.means.detach().numpy() * 250 + S[:3, 3], atol=1e-3)


def test_ops_keep_adam_moments_aligned():
    params, _, _ = _params(n=10)
    opt = ops.make_optimizer(params, {k: 0.01 for k in params.tensors()}, (0.9, 0.999))
    loss = sum((v * torch.arange(1, v.numel() + 1, dtype=v.dtype).view_as(v)).sum() for v in params.tensors().values())
    loss.backward()
    opt.step()
    before = {k: opt.state[v]["exp_avg"].clone() for k, v in params.tensors().items()}
    keep = torch.tensor([True, False] * 5)
    ops.select(params, opt, keep)
    for k, v in params.tensors().items():
        assert v.shape[0] == 5 and torch.equal(opt.state[v]["exp_avg"], before[k][keep])
        assert opt.param_groups[[g["name"] for g in opt.param_groups].index(k)]["params"][0] is v
    new = {k: v.detach()[:2].clone() for k, v in params.tensors().items()}
    ops.append(params, opt, new)
    for k, v in params.tensors().items():
        st = opt.state[v]
        assert v.shape[0] == 7
        assert torch.equal(st["exp_avg"][:5], before[k][keep]) and torch.all(st["exp_avg"][5:] == 0)
        assert torch.all(st["exp_avg_sq"][5:] == 0)
    # The optimizer still steps every (new) tensor.
    sum(v.sum() for v in params.tensors().values()).backward()
    opt.step()


def test_screen_gradient_is_resolution_normalised():
    g = torch.tensor([[1e-3, 0.0], [0.0, 2e-3]])
    assert torch.allclose(screen_grad_ndc(g, 400, 300), torch.tensor([0.2, 0.3], dtype=torch.float64))
    # The same NDC displacement at twice the resolution has half the pixel gradient per pixel
    # but twice the pixels: the normalised value is the same.
    assert torch.allclose(screen_grad_ndc(g / 2, 800, 600), screen_grad_ndc(g, 400, 300))


def test_strategy_clones_small_splits_large_and_respects_budget():
    params, _, _ = _params(n=6)
    with torch.no_grad():
        params.log_scales[:3] = math.log(0.001)  # small -> clone
        params.log_scales[3:] = math.log(0.05)  # large -> split
    opt = ops.make_optimizer(params, {k: 0.01 for k in params.tensors()}, (0.9, 0.999))
    st = DensifyStrategy(DensifyConfig.default(start_iter=0, stop_iter=100, every=10, grad_threshold=1e-3, reset_every=0,
                                               max_surfels=100))
    st.initialize(params.num)
    grad = torch.zeros(6, 2)
    grad[[0, 3], 0] = 1e-3  # NDC: 1e-3 * 400 / 2 = 0.2 > threshold
    st.step_post_backward(params, grad, torch.full((6,), 3, dtype=torch.int32), 400, 300)
    done = st.step_post_update(params, opt, 10, torch.Generator().manual_seed(0))
    assert done["cloned"] == 1 and done["split"] == 1
    assert params.num == 6 + 1 + 1  # one clone added; one split replaced by two children
    s = torch.exp(params.log_scales.detach())
    assert torch.allclose(s[-2:], torch.full((2, 2), 0.05 / 1.6, dtype=s.dtype))
    assert len(st.state.grad2d) == params.num and float(st.state.grad2d.sum()) == 0.0
    # Budget: no room -> nothing added.
    st.max_surfels = params.num  # the scene's budget (optimize.region), at most cfg.max_surfels
    st.step_post_backward(params, torch.full((params.num, 2), 1.0), torch.ones(params.num, dtype=torch.int32), 400, 300)
    done = st.step_post_update(params, opt, 20, torch.Generator().manual_seed(0))
    assert done["cloned"] + done["split"] == 0 and params.num <= st.max_surfels


def test_strategy_prunes_transparent_but_never_everything():
    params, _, _ = _params(n=5)
    opt = ops.make_optimizer(params, {k: 0.01 for k in params.tensors()}, (0.9, 0.999))
    with torch.no_grad():
        params.opacity_logits[:] = -10.0
    st = DensifyStrategy(DensifyConfig.default(start_iter=0, stop_iter=100, every=10, reset_every=0))
    st.initialize(5)
    done = st.step_post_update(params, opt, 10, torch.Generator())
    assert done["pruned"] == 4 and params.num == 1


def _ssim_slow(a: np.ndarray, b: np.ndarray) -> float:
    """Per-pixel SSIM with an explicit 11x11 Gaussian window and zero padding."""
    x = np.arange(11) - 5
    g = np.exp(-(x**2) / (2 * 1.5**2))
    w = np.outer(g, g) / g.sum() ** 2
    C, H, W = a.shape
    pa, pb = np.pad(a, ((0, 0), (5, 5), (5, 5))), np.pad(b, ((0, 0), (5, 5), (5, 5)))
    out = []
    for c in range(C):
        for i in range(H):
            for j in range(W):
                wa, wb = pa[c, i:i + 11, j:j + 11], pb[c, i:i + 11, j:j + 11]
                m1, m2 = (w * wa).sum(), (w * wb).sum()
                s11, s22, s12 = (w * wa * wa).sum() - m1 * m1, (w * wb * wb).sum() - m2 * m2, (w * wa * wb).sum() - m1 * m2
                out.append((2 * m1 * m2 + 1e-4) * (2 * s12 + 9e-4) / ((m1 * m1 + m2 * m2 + 1e-4) * (s11 + s22 + 9e-4)))
    return float(np.mean(out))


def test_ssim_matches_slow_reference_and_has_gradients():
    rng = np.random.default_rng(0)
    a, b = rng.random((3, 9, 13)), rng.random((3, 9, 13))
    ta = torch.tensor(a, requires_grad=True)
    assert abs(float(ssim(ta.detach(), torch.tensor(b))) - _ssim_slow(a, b)) < 1e-10
    assert abs(float(ssim(torch.tensor(a), torch.tensor(a))) - 1.0) < 1e-12
    assert torch.autograd.gradcheck(lambda x: ssim(x, torch.tensor(b)), (ta,))  # closed-form backward
    sa, sb = (torch.tensor(v[:, :5, :6], requires_grad=True) for v in (a, b))  # both: autograd through the blurs
    assert torch.autograd.gradcheck(lambda x, y: ssim(x, y), (sa, sb))


def test_ssim_closed_form_gradient_matches_autograd_at_training_size():
    """The closed-form backward of ``ssim(render, target)`` against autograd through the
    same forward (``target`` marked as needing a gradient takes that path), float32."""
    torch.manual_seed(0)
    a, b = torch.rand(3, 150, 200), torch.rand(3, 150, 200)
    x1 = a.clone().requires_grad_()
    ssim(x1, b).backward()
    x2, y2 = a.clone().requires_grad_(), b.clone().requires_grad_()
    ssim(x2, y2).backward()
    assert x1.grad.abs().max() > 0
    torch.testing.assert_close(x1.grad, x2.grad, rtol=1e-4, atol=1e-5 * float(x2.grad.abs().max()))


@pytest.mark.parametrize("shape", [(3, 150, 200), (1, 7, 9), (3, 11, 4), (2, 1, 1)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_ssim_kernels_are_the_torch_expressions_bit_for_bit(shape, dtype, monkeypatch):
    """The closed-form SSIM's per-pixel kernels (the CPU path) against its torch expressions:
    the same value and gradient to the last bit."""
    import pipeline.losses.photometric as photometric

    g = torch.Generator().manual_seed(3)
    a, b = torch.rand(shape, generator=g, dtype=dtype), torch.rand(shape, generator=g, dtype=dtype)
    results = []
    for fused in (True, False):
        monkeypatch.setattr(photometric, "_fused", lambda *_, f=fused: f)
        x = a.clone().requires_grad_()
        loss = ssim(x, b)
        loss.backward()
        results.append((loss, x.grad))
    (l1, g1), (l2, g2) = results
    assert torch.equal(l1, l2) and torch.equal(g1, g2)
    assert g1.abs().max() > 0


def _blur_slow(a: np.ndarray, window: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Each channel of ``(N, H, W)`` against the explicit 2-D Gaussian window, zero padding."""
    x = np.arange(window) - window // 2
    g = np.exp(-(x**2) / (2 * sigma**2))
    w2 = np.outer(g, g) / g.sum() ** 2
    p = window // 2
    N, H, W = a.shape
    pa = np.pad(a, ((0, 0), (p, p), (p, p)))
    out = np.empty_like(a)
    for c in range(N):
        for i in range(H):
            for j in range(W):
                out[c, i, j] = (w2 * pa[c, i:i + window, j:j + window]).sum()
    return out


@pytest.mark.parametrize("shape", [(2, 9, 13), (3, 4, 17), (1, 20, 3), (2, 1, 1)])
def test_blur_kernel_matches_the_slow_window_and_the_convolutions(shape):
    """SSIM's blur: the numba kernel against the explicit 2-D window and against torch's
    separable convolutions (images smaller than the window included), float64 and float32;
    a strided input is read as its values."""
    from pipeline.losses.photometric import _blur, _blur_torch, _gaussian_1d

    a = np.random.default_rng(1).random(shape)
    t = torch.tensor(a)
    g = _gaussian_1d(11, 1.5, t)
    np.testing.assert_allclose(_blur(t, g).numpy(), _blur_slow(a), rtol=0, atol=1e-13)
    torch.testing.assert_close(_blur(t, g), _blur_torch(t, g), rtol=0, atol=1e-13)
    t32 = t.float()
    torch.testing.assert_close(_blur(t32, g.float()), _blur_torch(t32, g.float()), rtol=0, atol=1e-6)
    wide = torch.tensor(np.random.default_rng(2).random((shape[0], shape[1], 2 * shape[2])))[:, :, ::2]
    torch.testing.assert_close(_blur(wide, g), _blur_torch(wide.contiguous(), g), rtol=0, atol=1e-13)


def test_blur_kernel_gradient():
    """The kernel's backward (the blur of the cotangent: the window is its own adjoint)."""
    from pipeline.losses.photometric import _blur, _gaussian_1d

    x = torch.tensor(np.random.default_rng(3).random((2, 7, 9)), requires_grad=True)
    g = _gaussian_1d(11, 1.5, x.detach())
    assert torch.autograd.gradcheck(lambda v: _blur(v, g), (x,))
    cot = torch.tensor(np.random.default_rng(4).random((2, 7, 9)))
    (_blur(x, g) * cot).sum().backward()
    np.testing.assert_allclose(x.grad.numpy(), _blur_slow(cot.numpy()), rtol=0, atol=1e-13)


def test_depth_to_normals_of_a_plane_faces_the_camera():
    K = torch.tensor([[50.0, 0, 16], [0, 55.0, 12], [0, 0, 1]], dtype=torch.float64)
    n_true = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)
    n_true = n_true / n_true.norm()
    # Plane n . x = -2 (in front of the camera, facing it): z = -2 / (n . K^-1 (x, y, 1)).
    ys, xs = torch.meshgrid(torch.arange(24.0, dtype=torch.float64), torch.arange(32.0, dtype=torch.float64), indexing="ij")
    rays = torch.linalg.inv(K) @ torch.stack([xs, ys, torch.ones_like(xs)]).reshape(3, -1)
    z = (-2.0 / (n_true @ rays)).reshape(24, 32)
    n = depth_to_normals(z, K)
    inner = n[:, 1:-1, 1:-1].reshape(3, -1)
    assert torch.allclose(inner, n_true[:, None].expand_as(inner), atol=1e-9)
    assert torch.all(n[:, 0] == 0) and torch.all(n[:, :, -1] == 0)
    z.requires_grad_(True)
    normal = n_true[:, None, None].expand(3, 24, 32).contiguous()
    alpha = torch.ones(24, 32, dtype=torch.float64)
    loss = depth_normal_loss(normal, z, alpha, K)
    assert float(loss.detach()) == pytest.approx(1 - (22 * 30) / (24 * 32), abs=1e-9)  # border pixels count 1
    small = z.detach()[:6, :7].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d: depth_normal_loss(normal[:, :6, :7], d, alpha[:6, :7], K), (small,))


def test_depth_normal_loss_gradient_is_finite_where_the_normal_vanishes():
    """A constant-zero depth patch has no normal (the cross product is 0): the loss there is
    1 and its gradient finite, not nan from 0 / 0."""
    K = torch.tensor([[50.0, 0, 3], [0, 50.0, 2.5], [0, 0, 1]], dtype=torch.float64)
    depth = torch.zeros(6, 7, dtype=torch.float64, requires_grad=True)
    normal = torch.zeros(3, 6, 7, dtype=torch.float64)
    normal[2] = -1.0
    loss = depth_normal_loss(normal, depth, torch.ones(6, 7, dtype=torch.float64), K)
    loss.backward()
    assert float(loss.detach()) == 1.0 and torch.isfinite(depth.grad).all()


def _layouts(base: torch.Tensor):
    """``base`` ``(H, W, 3)`` as a ``(3, H, W)`` leaf: the renders' permuted view and a contiguous copy."""
    leaf = base.clone().requires_grad_(True)
    yield leaf, leaf.permute(2, 0, 1)
    leaf = base.permute(2, 0, 1).contiguous().requires_grad_(True)
    yield leaf, leaf


@pytest.mark.parametrize("shape", [(120, 160), (7, 9), (3, 3), (2, 5)])
def test_depth_normal_kernels_are_the_torch_composition_bit_for_bit(shape):
    """L_dn's CPU kernels against its torch composition: value, normal and depth gradients to
    the last bit, with pixels of no depth, flat patches and zero normals in the maps."""
    from pipeline.losses.normal import _depth_normal_loss_torch

    H, W = shape
    g = torch.Generator().manual_seed(5)
    K = torch.tensor([[0.75 * W, 0.0, W / 2 - 0.5], [0.0, 0.78 * W, H / 2 - 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
    depth0 = 2.0 + 0.3 * torch.rand(H, W, generator=g)
    depth0[1:3, 1:4] = 0.0
    depth0[-3:, -2:] = 2.0
    base = torch.randn(H, W, 3, generator=g)
    base[:2, :2] = 0.0
    alpha = torch.rand(H, W, generator=g)
    for fn in (depth_normal_loss, _depth_normal_loss_torch):
        results = []
        for leaf, normal in _layouts(base):
            depth = depth0.clone().requires_grad_(True)
            loss = fn(normal, depth, alpha, K)
            assert ("_DepthNormalOnCPU" in type(loss.grad_fn).__name__) == (fn is depth_normal_loss and min(H, W) >= 3)
            (0.37 * loss).backward()
            results.append((loss.detach(), leaf.grad if leaf.shape[-1] == 3 else leaf.grad.permute(1, 2, 0), depth.grad))
        if fn is depth_normal_loss:
            kernels = results
    for got, want in zip(kernels, results):
        for a, b in zip(got, want):
            assert torch.equal(a, b)
    if H > 5:
        assert kernels[0][1].abs().max() > 0 and kernels[0][2].abs().max() > 0


@pytest.mark.parametrize("shape", [(120, 160), (7, 9), (2, 5), (1, 4)])
def test_normal_smoothness_kernels_are_the_torch_composition_bit_for_bit(shape):
    """L_smooth's CPU kernels against its torch composition, in both layouts the kernels take
    (torch sums the squares differently in each): value and gradient to the last bit, zero
    normals and masked pixels included."""
    from pipeline.losses.smoothness import _normal_smoothness_torch

    H, W = shape
    g = torch.Generator().manual_seed(6)
    base = torch.randn(H, W, 3, generator=g)
    base[:1, :2] = 0.0
    base[-1, -1] = 1e-13  # below F.normalize's eps: the clamp passes no gradient
    image = torch.rand(3, H, W, generator=g)
    valid = torch.rand(H, W, generator=g) > 0.3
    for leaf_k, normal_k in _layouts(base):
        loss_k = normal_smoothness_loss(normal_k, image, valid, 10.0)
        assert ("_SmoothnessOnCPU" in type(loss_k.grad_fn).__name__) == (H >= 2 and W >= 2)
        (0.41 * loss_k).backward()
        leaf_t = leaf_k.detach().clone().requires_grad_(True)
        normal_t = leaf_t.permute(2, 0, 1) if leaf_t.shape[-1] == 3 else leaf_t
        loss_t = _normal_smoothness_torch(normal_t, image, valid, 10.0)
        (0.41 * loss_t).backward()
        assert torch.equal(loss_k.detach(), loss_t.detach())
        assert torch.equal(leaf_k.grad, leaf_t.grad)
        if H * W > 10:
            assert loss_k > 0 and leaf_k.grad.abs().max() > 0


def test_mask_loss():
    alpha = torch.tensor([[0.2, 0.9]], requires_grad=True)
    mask = torch.tensor([[False, True]])
    assert float(mask_loss(alpha, mask).detach()) == pytest.approx((0.2 + 0.1) / 2)


@pytest.mark.parametrize("bad, match", [
    ({"every": 0}, "every must be >= 1"),
    ({"start_iter": 50, "stop_iter": 10}, "start_iter <= stop_iter"),
    ({"max_surfels": 0}, "max_surfels must be >= 1"),
    ({"split_factor": 1.0}, "split_factor must be > 1"),
    ({"reset_value": 0.0}, "reset_value must be in"),
    ({"grad_threshold": -1e-4}, "grad_threshold must be >= 0"),
])
def test_densify_config_refuses_values_that_break_the_strategy(bad, match):
    with pytest.raises(ConfigError, match=match):
        DensifyConfig.default(**bad)


def test_split_factor_sets_the_children_scale():
    """The one densification config reaches the strategy: a split child's scale is the
    parent's divided by ``split_factor``."""
    from pipeline.optimize.strategy import DensifyState

    rng = np.random.default_rng(0)
    params = init_params(rng.normal(size=(4, 3)), None, np.full((4, 3), 0.5), 0, 0.5, rng)
    opt = ops.make_optimizer(params, {k: 1e-3 for k in params.tensors()}, (0.9, 0.999))
    parent = torch.exp(params.log_scales[1].detach()).clone()
    state = DensifyState.zeros(4)
    ops.split(params, opt, state, torch.tensor([False, True, False, False]), 2.5, torch.Generator().manual_seed(0))
    assert params.num == 5 and len(state.count) == 5
    torch.testing.assert_close(torch.exp(params.log_scales[-2:].detach()), (parent / 2.5).expand(2, 2))


def test_mvs_depth_loss_matches_a_loop_and_gradcheck():
    rng = np.random.default_rng(1)
    depth = torch.tensor(2.0 + rng.random((5, 6)), dtype=torch.float64, requires_grad=True)
    mvs = torch.tensor(np.where(rng.random((5, 6)) < 0.3, 0.0, 2.0 + rng.random((5, 6))), dtype=torch.float64)
    valid = (mvs > 0) & torch.tensor(rng.random((5, 6)) < 0.8)
    ref = [abs(float(depth.detach()[y, x]) - float(mvs[y, x])) / float(mvs[y, x])
           for y in range(5) for x in range(6) if valid[y, x]]
    assert float(mvs_depth_loss(depth, mvs, valid).detach()) == pytest.approx(sum(ref) / len(ref), rel=1e-12)
    assert torch.autograd.gradcheck(lambda d: mvs_depth_loss(d + 1e-3, mvs, valid), (depth,))
    assert float(mvs_depth_loss(mvs.clone().requires_grad_(True), mvs, valid).detach()) == 0.0
    none = mvs_depth_loss(depth, mvs, torch.zeros_like(valid))
    assert float(none.detach()) == 0.0 and none.requires_grad


def test_mvs_depth_is_downscaled_without_averaging_across_edges_or_holes():
    from pipeline.optimize.views import _depth_at

    d = np.full((4, 8), 3.0)
    d[:, 6:] = 5.0  # an edge between footprints (columns 5|6) keeps both sides
    d[:, 5] = 5.0  # ... and this one inside the third footprint (columns 4-5)
    d[0, 0] = 0.0  # a hole in the first footprint
    out = _depth_at(d, 4, 2)
    np.testing.assert_allclose(out, [[0.0, 3.0, 0.0, 5.0], [3.0, 3.0, 0.0, 5.0]])
    np.testing.assert_array_equal(_depth_at(d, 8, 4), d)  # full size: unchanged


def test_visible_surfels_at_matches_a_loop():
    rng = np.random.default_rng(3)
    h, w = 9, 12
    K = torch.tensor([[10.0, 0, 5.5], [0, 10.0, 4.0], [0, 0, 1]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    depth = torch.from_numpy(rng.uniform(4, 6, (h, w)))
    depth[rng.uniform(size=(h, w)) < 0.2] = 0.0
    marked = torch.from_numpy(rng.uniform(size=(h, w)) < 0.5)
    # Surfels on the rendered surface (some pushed off it), some behind the camera or outside.
    n = 400
    u, v = rng.uniform(-2, w + 1, n), rng.uniform(-2, h + 1, n)
    z = np.where(rng.uniform(size=n) < 0.1, -1.0, 5.0)
    ui, vi = np.clip(np.round(u), 0, w - 1).astype(int), np.clip(np.round(v), 0, h - 1).astype(int)
    z = np.where(z > 0, np.where(depth.numpy()[vi, ui] > 0, depth.numpy()[vi, ui], 5.0), z)
    z *= 1 + rng.choice([0.0, 0.005, 0.02], n) * rng.choice([-1, 1], n)
    cam = np.stack([(u - 5.5) / 10 * z, (v - 4.0) / 10 * z, z], -1)
    means = torch.from_numpy(cam - T[:3, 3].numpy())  # world = camera - t (R = I)
    got = visible_surfels_at(means, K, T, depth, marked, 0.01).numpy()
    want = np.zeros(n, bool)
    for i in range(n):
        X = cam[i]
        if X[2] <= 0:
            continue
        px, py = round(10 * X[0] / X[2] + 5.5), round(10 * X[1] / X[2] + 4.0)
        if 0 <= px < w and 0 <= py < h and marked[py, px] and depth[py, px] > 0:
            want[i] = abs(X[2] - float(depth[py, px])) <= 0.01 * float(depth[py, px])
    assert (got == want).all()
    assert 20 < want.sum() < n - 20


def _smoothness_loop(n: torch.Tensor, img: torch.Tensor, valid: torch.Tensor, gamma: float) -> torch.Tensor:
    u = torch.nn.functional.normalize(n, dim=0)
    total, count = 0.0, 0
    _, H, W = n.shape
    for y in range(H):
        for x in range(W):
            for yy, xx in ((y, x + 1), (y + 1, x)):
                if yy < H and xx < W and valid[y, x] and valid[yy, xx]:
                    edge = (img[:, y, x] - img[:, yy, xx]).abs().mean()
                    total = total + (u[:, y, x] - u[:, yy, xx]).abs().sum() * torch.exp(-gamma * edge)
                    count += 1
    return total / max(count, 1)


def test_normal_smoothness_matches_a_loop_and_gradcheck():
    g = torch.Generator().manual_seed(3)
    n = torch.randn(3, 6, 7, dtype=torch.float64, generator=g).requires_grad_(True)
    img = torch.rand(3, 6, 7, dtype=torch.float64, generator=g)
    valid = torch.rand(6, 7, generator=g) > 0.3
    got = normal_smoothness_loss(n, img, valid, 10.0)
    assert torch.allclose(got, _smoothness_loop(n, img, valid, 10.0), rtol=1e-12, atol=1e-14)
    assert torch.autograd.gradcheck(lambda t: normal_smoothness_loss(t, img, valid, 10.0), (n,))


def test_normal_smoothness_spares_image_edges_and_ignores_length():
    # Two flat halves with different normals: the crease costs where the image is flat,
    # almost nothing where the image has an edge at the crease; scaling normals changes nothing.
    n = torch.zeros(3, 4, 6, dtype=torch.float64)
    n[2] = -1.0
    n[0, :, 3:] = 1.0
    valid = torch.ones(4, 6, dtype=torch.bool)
    flat = torch.full((3, 4, 6), 0.5, dtype=torch.float64)
    edge = flat.clone()
    edge[:, :, 3:] = 1.0
    on_flat = normal_smoothness_loss(n, flat, valid, 10.0)
    assert on_flat > 0
    assert normal_smoothness_loss(n, edge, valid, 10.0) < 0.01 * on_flat
    assert torch.allclose(normal_smoothness_loss(3.0 * n, flat, valid, 10.0), on_flat)
    assert normal_smoothness_loss(n, flat, torch.zeros_like(valid), 10.0) == 0


def _flat_loop(image: torch.Tensor, max_std: float, window: int) -> torch.Tensor:
    grey = image.mean(0)
    H, W = grey.shape
    r = window // 2
    out = torch.zeros(H, W, dtype=torch.bool)
    for i in range(H):
        for j in range(W):
            patch = grey[max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1]
            out[i, j] = patch.std(unbiased=False) < max_std
    return out


def test_flat_pixels_matches_a_pixel_loop_and_finds_the_flat_half():
    g = torch.Generator().manual_seed(3)
    img = torch.rand(3, 9, 11, dtype=torch.float64, generator=g) * 0.2
    img[:, :, :6] = 0.5 + 0.001 * img[:, :, :6]  # a nearly flat left part
    for max_std in (0.005, 0.03, 0.08):
        for window in (3, 5):
            assert torch.equal(flat_pixels(img, max_std, window), _flat_loop(img, max_std, window))
    flat = flat_pixels(img, 0.005)
    assert flat[:, :4].all() and not flat[:, 8:].any()
