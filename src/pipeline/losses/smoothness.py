"""The edge-aware normal smoothness term L_smooth and the flat-image pixels it is taken on.
Torch, differentiable, any float dtype; normal maps ``(3, H, W)`` in the OpenCV camera frame,
images ``(C, H, W)``. On the CPU in float32, L_smooth's per-pixel work runs in
:mod:`._smooth_kernels` (torch's value and gradient bit for bit).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.losses import _smooth_kernels

def flat_pixels(image: torch.Tensor, max_std: float, window: int = 5) -> torch.Tensor:
    """``(H, W)`` bool: pixels whose ``window`` x ``window`` grey std (channel mean of
    ``image`` ``(C, H, W)``; the window cut at the border) is below ``max_std``."""
    grey = image.detach().mean(0, keepdim=True)[None]
    pad = window // 2
    ones = torch.ones_like(grey)
    n = F.avg_pool2d(ones, window, 1, pad, count_include_pad=True)
    m1 = F.avg_pool2d(grey, window, 1, pad, count_include_pad=True) / n
    m2 = F.avg_pool2d(grey * grey, window, 1, pad, count_include_pad=True) / n
    return ((m2 - m1 * m1).clamp_min(0).sqrt() < max_std)[0, 0]


def normal_smoothness_loss(normal: torch.Tensor, image: torch.Tensor, valid: torch.Tensor, gamma: float) -> torch.Tensor:
    """Edge-aware smoothness of a normal map: over the pairs of 4-neighbour pixels that are
    both ``valid``, the mean of ``|n_p - n_q|_1 exp(-gamma |I_p - I_q|)`` (unit normals,
    ``|I_p - I_q|`` the mean absolute difference over the channels), so normals agree where
    the image is flat and may turn at image edges. ``normal``: ``(3, H, W)``; ``image``:
    ``(C, H, W)``; ``valid``: ``(H, W)`` bool. 0 (connected to ``normal``) without pairs."""
    image = image.detach()
    fma = _kernel_layout(normal)
    if fma is None:
        return _normal_smoothness_torch(normal, image, valid, gamma)
    (pairs_v, weight_v), (pairs_h, weight_h) = (_pairs_and_weights(image, valid, gamma, dim) for dim in (1, 2))
    count = int(pairs_v.sum()) + int(pairs_h.sum())
    return _SmoothnessOnCPU.apply(normal, weight_v, weight_h, pairs_v, pairs_h, count, fma)


def _pairs_and_weights(
    image: torch.Tensor, valid: torch.Tensor, gamma: float, dim: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Along ``dim`` of a ``(C, H, W)`` map (1: vertical, 2: horizontal neighbours): which
    pairs are both valid, and their edge weights ``exp(-gamma |I_p - I_q|)``."""
    size = image.shape[dim] - 1
    pairs = valid.narrow(dim - 1, 0, size) & valid.narrow(dim - 1, 1, size)
    edge = (image.narrow(dim, 0, size) - image.narrow(dim, 1, size)).abs().mean(0)
    return pairs, torch.exp(-gamma * edge)


def _kernel_layout(normal: torch.Tensor) -> bool | None:
    """Whether the kernels take ``normal`` and how torch sums its squares: ``True`` for the
    renders' ``(H, W, 3)`` seen as ``(3, H, W)`` (fused multiply-adds), ``False`` for a
    contiguous ``(3, H, W)``, ``None`` for the torch composition (another device, dtype or
    layout, or a map under 2 x 2)."""
    if normal.device.type != "cpu" or normal.dtype != torch.float32 or normal.dim() != 3 or normal.shape[0] != 3:
        return None
    _, H, W = normal.shape
    if H < 2 or W < 2:
        return None
    if normal.stride() == (1, 3 * W, 3):
        return True
    return False if normal.is_contiguous() else None


class _SmoothnessOnCPU(torch.autograd.Function):
    """L_smooth through :mod:`._smooth_kernels`; the sums over the map stay torch's."""

    @staticmethod
    def forward(ctx, normal, weight_v, weight_h, pairs_v, pairs_h, count, fma):
        x = normal.detach().permute(1, 2, 0).numpy()
        H, W = x.shape[:2]
        clamped, unit = np.empty((H, W), np.float32), np.empty((H, W, 3), np.float32)
        cost_v, cost_h = np.empty((H - 1, W), np.float32), np.empty((H, W - 1), np.float32)
        maps = tuple(t.contiguous().numpy() for t in (weight_v, weight_h, pairs_v, pairs_h))
        _smooth_kernels.forward(x, *maps, fma, clamped, unit, cost_v, cost_h)
        total = normal.detach().sum() * 0.0
        total = total + torch.from_numpy(cost_v).sum()
        total = total + torch.from_numpy(cost_h).sum()
        ctx.save_for_backward(normal)
        ctx.kernel_state = (maps, fma, clamped, unit, count)
        return total / max(count, 1)

    @staticmethod
    def backward(ctx, grad):
        (normal,) = ctx.saved_tensors
        maps, fma, clamped, unit, count = ctx.kernel_state
        x = normal.detach().permute(1, 2, 0).numpy()
        H, W = x.shape[:2]
        g_pair = np.float32((grad / max(count, 1)).item())
        g_v, g_h = np.empty((H - 1, W, 3), np.float32), np.empty((H, W - 1, 3), np.float32)
        g_x = np.empty((H, W, 3), np.float32)
        _smooth_kernels.backward(x, *maps, fma, clamped, unit, g_pair, g_v, g_h, g_x)
        return torch.from_numpy(g_x).permute(2, 0, 1), None, None, None, None, None, None


def _normal_smoothness_torch(normal: torch.Tensor, image: torch.Tensor, valid: torch.Tensor,
                             gamma: float) -> torch.Tensor:
    """:func:`normal_smoothness_loss` composed of torch operations: the reference of the
    kernels, and the path off the CPU and in other dtypes."""
    n = F.normalize(normal, dim=0)
    total, count = normal.sum() * 0.0, 0
    for dim in (1, 2):
        size = n.shape[dim] - 1
        a, b = n.narrow(dim, 0, size), n.narrow(dim, 1, size)
        ok, weight = _pairs_and_weights(image, valid, gamma, dim)
        cost = (a - b).abs().sum(0) * weight
        total = total + torch.where(ok, cost, torch.zeros_like(cost)).sum()
        count += int(ok.sum())
    return total / max(count, 1)
