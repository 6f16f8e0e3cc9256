"""The photometric term: L1 plus D-SSIM between a render and its input image (3DGS/2DGS).
Torch, differentiable, any float dtype; images ``(3, H, W)``.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.losses import _ssim_kernels
from pipeline.losses._blur_kernels import gaussian_blur

SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def _gaussian_1d(size: int, sigma: float, like: torch.Tensor) -> torch.Tensor:
    x = torch.arange(size, dtype=like.dtype, device=like.device) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


def _blur_torch(stack: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The separable Gaussian ``g`` over each channel of ``(N, H, W)``, zero padding: two 1-D
    depthwise convolutions (any device; the reference of :mod:`._blur_kernels`)."""
    n, window = stack.shape[0], g.shape[0]
    pad = window // 2
    out = F.conv2d(stack.unsqueeze(0), g.view(1, 1, 1, -1).expand(n, 1, 1, window), padding=(0, pad), groups=n)
    return F.conv2d(out, g.view(1, 1, -1, 1).expand(n, 1, window, 1), padding=(pad, 0), groups=n)[0]


def _blur_numba(stack: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    src = stack.detach().contiguous().numpy()
    out = np.empty_like(src)
    gaussian_blur(src, g.detach().numpy(), np.empty_like(src), out)
    return torch.from_numpy(out)


class _Blur(torch.autograd.Function):
    """:func:`_blur_numba` for autograd: the symmetric zero-padded blur is its own adjoint."""

    @staticmethod
    def forward(ctx, stack, g):
        ctx.save_for_backward(g)
        return _blur_numba(stack, g)

    @staticmethod
    def backward(ctx, grad):
        (g,) = ctx.saved_tensors
        return _blur_numba(grad, g), None


def _blur(stack: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
    """The separable Gaussian ``g`` (symmetric) over each channel of ``(N, H, W)``, zero
    padding: the numba kernel on the CPU, the torch convolutions elsewhere."""
    if stack.device.type != "cpu" or g.requires_grad:
        return _blur_torch(stack, g)
    return _Blur.apply(stack, g) if stack.requires_grad else _blur_numba(stack, g)


def _ssim_parts(img1: torch.Tensor, img2: torch.Tensor, g: torch.Tensor):
    """The local moments and the SSIM map's numerator and denominator factors."""
    C = img1.shape[0]
    mu1, mu2, e11, e22, e12 = _blur(torch.cat([img1, img2, img1 * img1, img2 * img2, img1 * img2]), g).split(C)
    a1 = 2 * mu1 * mu2 + SSIM_C1
    a2 = 2 * (e12 - mu1 * mu2) + SSIM_C2
    b1 = mu1 * mu1 + mu2 * mu2 + SSIM_C1
    b2 = (e11 - mu1 * mu1) + (e22 - mu2 * mu2) + SSIM_C2
    return mu1, mu2, a1, a2, b1, b2


class _SSIMOfFirst(torch.autograd.Function):
    """Mean SSIM differentiable in the first image only (the render against a constant
    target), with its gradient in closed form. Per pixel the map ``a1 a2 / (b1 b2)`` moves
    with the blurred moments ``mu1``, ``E[x^2]`` and ``E[xy]``; each moment's sensitivity is
    blurred back (the window is its own adjoint) and chained to ``x``: three blurs in place
    of the convolutions' backward, which costs several times their forward here. On the CPU
    the per-pixel arithmetic runs in :mod:`._ssim_kernels` (the same operations and results
    as the torch expressions here, in one pass each)."""

    @staticmethod
    def forward(ctx, img1, img2, g):
        if _fused(img1, img2):
            mu1, mu2, a1, a2, b1, b2, ssim_map = _ssim_parts_fused(img1, img2, g)
        else:
            mu1, mu2, a1, a2, b1, b2 = _ssim_parts(img1, img2, g)
            ssim_map = a1 * a2 / (b1 * b2)
        ctx.save_for_backward(img1, img2, g, mu1, mu2, a1, a2, b1, b2, ssim_map)
        return ssim_map.mean()

    @staticmethod
    def backward(ctx, grad):
        img1, img2, g, mu1, mu2, a1, a2, b1, b2, ssim_map = ctx.saved_tensors
        scale = grad / ssim_map.numel()
        C = img1.shape[0]
        if _fused(img1, img2):
            np_dtype = _np_dtype(img1)
            two, n = np_dtype.type(2), img1.numel()
            sens = np.empty(3 * n, np_dtype)
            _ssim_kernels.sensitivities(*(_flat(t) for t in (mu1, mu2, a1, a2, b1, b2, ssim_map)),
                                        np_dtype.type(scale.item()), two, sens)
            blurred = _blur_numba(torch.from_numpy(sens).view(3 * C, *img1.shape[1:]), g).numpy().reshape(-1)
            out = np.empty(n, np_dtype)
            _ssim_kernels.chain(blurred, _flat(img1), _flat(img2), two, out)
            return torch.from_numpy(out).view(img1.shape), None, None
        inv = scale / (b1 * b2)
        d_mu1 = 2 * mu2 * (a2 - a1) * inv - 2 * mu1 * ssim_map * (b2 - b1) * inv
        d_e11 = -ssim_map * scale / b2
        d_e12 = 2 * a1 * inv
        g_mu1, g_e11, g_e12 = _blur(torch.cat([d_mu1, d_e11, d_e12]), g).split(C)
        return g_mu1 + 2 * img1 * g_e11 + img2 * g_e12, None, None


def _fused(img1: torch.Tensor, img2: torch.Tensor) -> bool:
    return (img1.device.type == "cpu" and img2.device == img1.device and img2.dtype == img1.dtype
            and img1.dtype in (torch.float32, torch.float64))


def _np_dtype(t: torch.Tensor) -> np.dtype:
    return np.dtype(np.float32 if t.dtype == torch.float32 else np.float64)


def _flat(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy().reshape(-1)


def _ssim_parts_fused(img1: torch.Tensor, img2: torch.Tensor, g: torch.Tensor):
    """:func:`_ssim_parts` and the SSIM map through :mod:`._ssim_kernels` (CPU)."""
    C, n, np_dtype = img1.shape[0], img1.numel(), _np_dtype(img1)
    stack = np.empty(5 * n, np_dtype)
    _ssim_kernels.moments_input(_flat(img1), _flat(img2), stack)
    blurred = _blur_numba(torch.from_numpy(stack).view(5 * C, *img1.shape[1:]), g).numpy().reshape(-1)
    a1, a2, b1, b2, ssim_map = (np.empty(n, np_dtype) for _ in range(5))
    two, c1, c2 = (np_dtype.type(v) for v in (2, SSIM_C1, SSIM_C2))
    _ssim_kernels.parts(blurred, two, c1, c2, a1, a2, b1, b2, ssim_map)
    maps = (blurred[:n], blurred[n:2 * n], a1, a2, b1, b2, ssim_map)
    return tuple(torch.from_numpy(m).view(img1.shape) for m in maps)


def ssim(img1: torch.Tensor, img2: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two ``(C, H, W)`` images in [0, 1] (Wang et al. 2004; 11x11 Gaussian
    window, sigma 1.5, zero padding as 3DGS/2DGS). Differentiable in both; when only
    ``img1`` needs a gradient (a render against its target) the gradient is in closed form
    (:class:`_SSIMOfFirst`)."""
    g = _gaussian_1d(window, sigma, img1)
    if img1.requires_grad and not img2.requires_grad:
        return _SSIMOfFirst.apply(img1, img2, g)
    _, _, a1, a2, b1, b2 = _ssim_parts(img1, img2, g)
    return (a1 * a2 / (b1 * b2)).mean()


def photometric_loss(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``((1 - lambda) L1 + lambda (1 - SSIM), L1)`` of two ``(3, H, W)`` images."""
    l1 = (render - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(render, target)), l1
