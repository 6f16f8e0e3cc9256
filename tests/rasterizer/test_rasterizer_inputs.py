"""Input validation and the spherical-harmonics basis."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.errors import ConfigError
from pipeline.rasterizer import Camera, Surfels, rasterize
from pipeline.rasterizer.project import eval_sh


def good(P=3, C=3, dtype=torch.float64) -> dict:
    return dict(
        means=torch.zeros(P, 3, dtype=dtype) + torch.tensor([0, 0, 3.0], dtype=dtype),
        quats=torch.tensor([[1.0, 0, 0, 0]] * P, dtype=dtype),
        scales=torch.full((P, 2), 0.1, dtype=dtype),
        opacities=torch.full((P,), 0.5, dtype=dtype),
        features=torch.ones(P, C, dtype=dtype),
    )


CAM = dict(K=np.array([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]]), world_to_cam=np.eye(4), width=10, height=10)


@pytest.mark.parametrize(
    "field,value,message",
    [
        ("means", torch.zeros(3, 2, dtype=torch.float64), "means must be"),
        ("quats", torch.zeros(2, 4, dtype=torch.float64), "quats must be"),
        ("scales", torch.zeros(3, 3, dtype=torch.float64), "scales must be"),
        ("opacities", torch.zeros(3, 1, dtype=torch.float64), "opacities must be"),
        ("features", torch.zeros(3, dtype=torch.float64), "features must be"),
        ("means", torch.tensor([[0, 0, float("nan")]] * 3, dtype=torch.float64), "non-finite"),
        ("features", torch.tensor([[0, float("inf"), 0]] * 3, dtype=torch.float64), "non-finite"),
        ("scales", torch.tensor([[0.1, -0.1]] * 3, dtype=torch.float64), "scales must be > 0"),
        ("opacities", torch.tensor([0.5, 1.5, 0.5], dtype=torch.float64), "opacities must lie in"),
        ("opacities", torch.tensor([0.5, -1e-9, 0.5], dtype=torch.float64), "opacities must lie in"),
        ("opacities", torch.tensor([0.5, float("nan"), 0.5], dtype=torch.float64), "non-finite"),
        ("scales", torch.tensor([[0.1, 0.1], [float("-inf"), 0.1], [0.1, 0.1]], dtype=torch.float64), "non-finite"),
        ("quats", torch.tensor([[0.0, 0, 0, 0]] * 3, dtype=torch.float64), "zero quaternion"),
        ("means", torch.zeros(3, 3, dtype=torch.float32), "all fields must be"),
        ("means", torch.zeros(3, 3, dtype=torch.int64), "float32 or float64"),
    ],
)
def test_bad_surfels_raise(field, value, message):
    kw = good()
    kw[field] = value
    with pytest.raises(ValueError, match=message):
        Surfels(**kw)


def test_finite_values_whose_sum_overflows_are_accepted():
    """The finiteness check sums first; an overflowing sum of finite values is not an error."""
    kw = good(dtype=torch.float32)
    kw["means"] = torch.tensor([[3e38, 0, 3.0]] * 3, dtype=torch.float32)
    kw["features"] = torch.full((3, 3), 3e38, dtype=torch.float32)
    assert not torch.isfinite(kw["means"].sum())
    Surfels(**kw)
    kw["features"][1, 2] = float("nan")
    with pytest.raises(ValueError, match="features has non-finite"):
        Surfels(**kw)


def test_bad_sh_raise():
    kw = good()
    kw["features"] = torch.zeros(3, 4, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match="SH coefficients"):
        Surfels(**kw, sh_degree=2)  # needs 9 coefficients
    with pytest.raises(ValueError, match="sh_degree"):
        Surfels(**kw, sh_degree=4)


@pytest.mark.parametrize(
    "change,message",
    [
        (dict(K=np.eye(2)), "K must be 3x3"),
        (dict(K=np.array([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 2]])), "last row"),
        (dict(K=np.array([[-10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]])), "positive focal"),
        (dict(K=np.array([[10.0, 0, np.nan], [0, 10.0, 5], [0, 0, 1]])), "non-finite"),
        (dict(world_to_cam=np.diag([1.0, 1.0, 2.0, 1.0])), "rotation"),
        (dict(world_to_cam=np.diag([1.0, 1.0, -1.0, 1.0])), "rotation"),
        (dict(world_to_cam=np.eye(3)), "4x4"),
        (dict(width=0), "width"),
        (dict(height=2.5), "height"),
        (dict(near=0.0), "near < far"),
        (dict(near=2.0, far=1.0), "near < far"),
    ],
)
def test_bad_camera_raises(change, message):
    with pytest.raises(ValueError, match=message):
        Camera(**{**CAM, **change})


def test_bad_call_raises():
    s, cam = Surfels(**good()), Camera(**CAM)
    with pytest.raises(ValueError, match="unknown backend"):
        rasterize(s, cam, backend="opengl")
    with pytest.raises(ValueError, match="depth_eps"):
        rasterize(s, cam, depth_eps=float("nan"))
    with pytest.raises(ValueError, match="reference_block"):
        rasterize(s, cam, backend="cpu", reference_block=8)


def test_sh_basis_is_orthonormal():
    """The 16 real SH basis functions (3DGS signs) integrate to the identity over the
    sphere; checked by quadrature on a Fibonacci sphere."""
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi, theta = torch.arccos(1 - 2 * i / n), math.pi * (1 + math.sqrt(5)) * i
    dirs = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], 1)
    basis = []
    for k in range(16):
        sh = torch.zeros(n, 16, 3, dtype=torch.float64)
        sh[:, k, 0] = 0.1  # small enough that the clamp at 0 never acts (|Y| < 1.1)
        basis.append((eval_sh(3, sh, dirs)[:, 0] - 0.5) / 0.1)
    Y = torch.stack(basis, 1)
    gram = 4 * math.pi * Y.T @ Y / n
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=2e-3)


def test_sh_degree_zero_is_the_dc_colour():
    sh = torch.tensor([[[0.3, -0.2, 1.0]]], dtype=torch.float64)
    col = eval_sh(0, sh, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert col.tolist()[0] == pytest.approx([0.28209479177387814 * 0.3 + 0.5, 0.28209479177387814 * -0.2 + 0.5,
                                             0.28209479177387814 + 0.5])  # fmt: skip


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message given without CUDA")
def test_cuda_backend_without_cuda_raises():
    with pytest.raises(ValueError, match="CUDA device"):
        rasterize(Surfels(**good(dtype=torch.float32)), Camera(**CAM), backend="cuda")


def test_auto_backend_is_a_cpu_backend_and_cuda_without_a_device_is_refused():
    # auto never picks cuda, also where a GPU is: gsplat's centre depth is another method
    # (docs/rasterizer.md, "The cuda backend, run").
    from pipeline.rasterizer import resolve_backend, simd

    assert resolve_backend("auto") == ("simd" if simd.available()[0] else "cpu")
    assert resolve_backend("reference") == "reference"
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA device"):
            resolve_backend("cuda")
