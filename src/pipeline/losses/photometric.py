"""The photometric term: L1 plus D-SSIM between a render and its input image (3DGS/2DGS).
Torch, differentiable, any float dtype; images ``(3, H, W)``.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

SSIM_C1 = 0.01 ** 2
SSIM_C2 = 0.03 ** 2


def _gaussian_1d(size: int, sigma: float, like: torch.Tensor) -> torch.Tensor:
    x = torch.arange(size, dtype=like.dtype, device=like.device) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


def ssim(img1: torch.Tensor, img2: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of two ``(C, H, W)`` images in [0, 1] (Wang et al. 2004; 11x11 Gaussian
    window, sigma 1.5, zero padding as 3DGS/2DGS). The window is separable: two 1-D passes
    over the five moment images at once (11x fewer taps than the 2-D convolution)."""
    C = img1.shape[0]
    g = _gaussian_1d(window, sigma, img1)
    pad = window // 2
    stack = torch.cat([img1, img2, img1 * img1, img2 * img2, img1 * img2]).unsqueeze(0)  # (1, 5C, H, W)
    n = stack.shape[1]
    blur = F.conv2d(stack, g.view(1, 1, 1, -1).expand(n, 1, 1, window), padding=(0, pad), groups=n)
    blur = F.conv2d(blur, g.view(1, 1, -1, 1).expand(n, 1, window, 1), padding=(pad, 0), groups=n)
    mu1, mu2, e11, e22, e12 = blur[0].split(C)
    s11, s22, s12 = e11 - mu1 * mu1, e22 - mu2 * mu2, e12 - mu1 * mu2
    num = (2 * mu1 * mu2 + SSIM_C1) * (2 * s12 + SSIM_C2)
    den = (mu1 * mu1 + mu2 * mu2 + SSIM_C1) * (s11 + s22 + SSIM_C2)
    return (num / den).mean()


def photometric_loss(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``((1 - lambda) L1 + lambda (1 - SSIM), L1)`` of two ``(3, H, W)`` images."""
    l1 = (render - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(render, target)), l1
