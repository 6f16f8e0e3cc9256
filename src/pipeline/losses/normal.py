"""Normal terms: GCGS normal-prior consistency L_nor (Eq. 10-12: L_nc and L_ngc, see
docs/priors.md) and 2DGS depth-normal consistency. Differentiable torch functions; any
float dtype. Normal maps are ``(3, H, W)`` in the OpenCV camera frame, facing the camera
(``n . ray < 0``); depth maps ``(H, W)`` camera-frame z. On the CPU in float32, L_dn's
per-pixel work runs in :mod:`._dn_kernels` (torch's value and gradients bit for bit).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.losses import _dn_kernels

_SOBEL_X = np.array([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0


def sobel(img: torch.Tensor) -> torch.Tensor:
    """Sobel derivatives of a ``(C, H, W)`` image: ``(2, C, H, W)`` as (d/dx, d/dy).

    The kernel is divided by 8 so that a linear ramp of slope 1 per pixel gives 1.
    Borders replicate the edge pixels (gradients there are not used, see below).
    """
    C = img.shape[0]
    kx = torch.as_tensor(_SOBEL_X, dtype=img.dtype, device=img.device)
    k = torch.stack([kx, kx.t()]).unsqueeze(1).repeat(C, 1, 1, 1)  # (2C, 1, 3, 3)
    x = F.pad(img.unsqueeze(0), (1, 1, 1, 1), mode="replicate")
    g = F.conv2d(x, k, groups=C)  # (1, 2C, H, W) ordered (c0 dx, c0 dy, c1 dx, ...)
    return g.view(C, 2, *img.shape[1:]).transpose(0, 1)


def normal_consistency_losses(
    n_render: torch.Tensor, n_prior: torch.Tensor, valid_mask: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Normal losses of GCGS Eq. 10-12: ``(L_nc, L_ngc)``.

    ``L_nc`` = mean over valid pixels M of ``||n_render - n_prior||_1`` (sum of absolute
    differences of the 3 components). ``L_ngc`` = mean of ``||S(n_render) - S(n_prior)||^2``
    over the 6 Sobel derivatives (x and y of each component), taken over the pixels of M
    whose whole 3x3 neighbourhood is in M, so that no derivative mixes in invalid pixels.
    Both normal maps are ``(3, H, W)`` in the same (camera) frame; ``valid_mask`` is
    ``(H, W)`` bool. An empty set gives 0.
    """
    if n_render.shape != n_prior.shape or n_render.shape[0] != 3 or n_render.shape[1:] != valid_mask.shape:
        raise ValueError(
            f"normal maps must both be (3, H, W) with an (H, W) mask; got {tuple(n_render.shape)}, "
            f"{tuple(n_prior.shape)}, {tuple(valid_mask.shape)}"
        )
    m = valid_mask.to(device=n_render.device).bool()
    n_prior = n_prior.to(n_render)
    diff = (n_render - n_prior).abs().sum(0)
    l_nc = diff[m].sum() / m.sum().clamp_min(1)
    # 3x3 erosion of M: min-pool is -maxpool(-x); pad with "invalid" at the borders.
    inner = -F.max_pool2d(-F.pad(m[None, None].float(), (1, 1, 1, 1), value=0.0), 3, stride=1)
    inner = inner[0, 0] > 0.5
    g = sobel(n_render) - sobel(n_prior)
    gsq = (g * g).sum(dim=(0, 1))
    l_ngc = gsq[inner].sum() / inner.sum().clamp_min(1)
    return l_nc, l_ngc


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
    maps = (normal_render, depth, alpha)
    H, W = depth.shape
    if all(t.device.type == "cpu" and t.dtype == torch.float32 for t in maps) and H >= 3 and W >= 3:
        return _DepthNormalOnCPU.apply(normal_render, depth, alpha.detach(), torch.linalg.inv(K.to(depth.dtype)))
    return _depth_normal_loss_torch(normal_render, depth, alpha, K)


class _DepthNormalOnCPU(torch.autograd.Function):
    """L_dn through :mod:`._dn_kernels`; the mean over the map stays torch's."""

    @staticmethod
    def forward(ctx, normal_render, depth, alpha, Kinv):
        H, W = depth.shape
        arrays = (depth.detach().contiguous().numpy(), normal_render.detach().permute(1, 2, 0).numpy(),
                  alpha.contiguous().numpy(), Kinv.contiguous().numpy())
        points, n_depth = np.empty((3, H, W), np.float32), np.empty((3, H, W), np.float32)
        inv, cross = np.empty((H - 2, W - 2), np.float32), np.empty((3, H - 2, W - 2), np.float32)
        out = np.empty((H, W), np.float32)
        _dn_kernels.forward(*arrays, points, n_depth, inv, cross, out)
        ctx.save_for_backward(normal_render, depth)
        ctx.kernel_state = (arrays, points, n_depth, inv, cross)
        return torch.from_numpy(out).mean()

    @staticmethod
    def backward(ctx, grad):
        _ = ctx.saved_tensors  # torch's check that the maps were not changed in place
        arrays, points, n_depth, inv, cross = ctx.kernel_state
        H, W = arrays[0].shape
        g_mean = np.float32((grad / (H * W)).item())
        g_normal, g_depth = np.empty((H, W, 3), np.float32), np.empty((H, W), np.float32)
        g_a, g_b = np.empty((3, H - 2, W - 2), np.float32), np.empty((3, H - 2, W - 2), np.float32)
        _dn_kernels.backward(*arrays, points, n_depth, inv, cross, g_mean, g_normal, g_a, g_b, g_depth)
        return torch.from_numpy(g_normal).permute(2, 0, 1), torch.from_numpy(g_depth), None, None


def _depth_normal_loss_torch(normal_render: torch.Tensor, depth: torch.Tensor, alpha: torch.Tensor,
                             K: torch.Tensor) -> torch.Tensor:
    """:func:`depth_normal_loss` composed of torch operations: the reference of the kernels,
    and the path off the CPU and in other dtypes."""
    n_d = depth_to_normals(depth, K)
    dot = normal_render[0] * n_d[0] + normal_render[1] * n_d[1] + normal_render[2] * n_d[2]
    return (1.0 - dot * alpha.detach()).mean()
