"""The edge-aware normal smoothness term L_smooth and the flat-image pixels it is taken on.
Torch, differentiable, any float dtype; normal maps ``(3, H, W)`` in the OpenCV camera frame,
images ``(C, H, W)``.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

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
    n = F.normalize(normal, dim=0)
    image = image.detach()
    total, count = normal.sum() * 0.0, 0
    for dim in (1, 2):
        size = n.shape[dim] - 1
        a, b = n.narrow(dim, 0, size), n.narrow(dim, 1, size)
        ok = valid.narrow(dim - 1, 0, size) & valid.narrow(dim - 1, 1, size)
        edge = (image.narrow(dim, 0, size) - image.narrow(dim, 1, size)).abs().mean(0)
        cost = (a - b).abs().sum(0) * torch.exp(-gamma * edge)
        total = total + torch.where(ok, cost, torch.zeros_like(cost)).sum()
        count += int(ok.sum())
    return total / max(count, 1)
