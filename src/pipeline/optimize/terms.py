"""Rendering losses of the training loop that the priors module does not define:
D-SSIM, 2DGS depth-normal consistency, the mask term. Torch, differentiable, any float
dtype. Images are ``(3, H, W)``; depth maps ``(H, W)`` camera-frame z; normals ``(3, H, W)``
in the OpenCV camera frame, facing the camera (``n . ray < 0``).
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


def depth_to_normals(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Unit normals ``(3, H, W)`` of the surface a depth map (camera z) describes, from
    central differences of the back-projected points, facing the camera; 0 on the one-pixel
    border and wherever the cross product vanishes.

    Written channel by channel: torch's reductions and cross products over an axis of 3 are
    several times slower here than the same sums spelled out (docs/speed_accuracy.md)."""
    H, W = depth.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=depth.dtype), torch.arange(W, dtype=depth.dtype), indexing="ij")
    Kinv = torch.linalg.inv(K.to(depth.dtype))
    px, py, pz = ((Kinv[i, 0] * xs + Kinv[i, 1] * ys + Kinv[i, 2]) * depth for i in range(3))

    def central(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return c[1:-1, 2:] - c[1:-1, :-2], c[2:, 1:-1] - c[:-2, 1:-1]

    (ax, bx), (ay, by), (az, bz) = central(px), central(py), central(pz)
    # n = dy x dx faces the camera in OpenCV axes (x right, y down, z forward).
    nx, ny, nz = by * az - bz * ay, bz * ax - bx * az, bx * ay - by * ax
    sq = nx * nx + ny * ny + nz * nz
    nonzero = sq > 0
    # rsqrt of a safe value, then zeroed: no inf or nan reaches the gradient where n vanishes.
    inv = torch.where(nonzero, torch.rsqrt(torch.where(nonzero, sq, torch.ones_like(sq))), torch.zeros_like(sq))
    return F.pad(torch.stack([nx * inv, ny * inv, nz * inv]), (1, 1, 1, 1))


def depth_normal_loss(normal_render: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """2DGS depth-normal consistency: mean over pixels of ``1 - n_render . (N_d alpha)``,
    with ``normal_render`` the alpha-blended (not renormalised) normal and ``N_d`` the
    normal of the rendered depth, weighted by the detached alpha."""
    n_d = depth_to_normals(depth, K)
    dot = normal_render[0] * n_d[0] + normal_render[1] * n_d[1] + normal_render[2] * n_d[2]
    return (1.0 - dot * alpha.detach()).mean()


def mvs_depth_loss(depth: torch.Tensor, mvs_depth: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean ``|depth - mvs_depth| / mvs_depth`` over ``valid`` pixels (all ``(H, W)``; 0 when
    none is valid): relative, so it means the same at every resolution and scale."""
    if not bool(valid.any()):
        return depth.sum() * 0.0
    d, m = depth[valid], mvs_depth[valid].to(depth)
    return ((d - m).abs() / m).mean()


def mask_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean ``|alpha - mask|``: background pixels pull alpha to 0, object pixels to 1."""
    return (alpha - mask.to(alpha)).abs().mean()


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
