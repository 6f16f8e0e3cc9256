"""The ``reference`` backend: dense pure PyTorch with autograd, the oracle for tests.

Every (pixel, surfel) pair is evaluated; the skip and stop rules are masks:

* skip a pair when its intersection depth ``z < near``, ``alpha < 1/255`` or ``rho > 9``
  (beyond 3 sigma);
* stop a pixel at the first pair whose next transmittance ``T (1 - alpha) < 1e-4``
  (that pair and every later one are dropped). The inclusive transmittance is
  non-increasing, so "dropped" is simply ``cumprod(1 - alpha) < 1e-4``.

With ``block=None`` all surfels whose centre depth is in ``[near, far]`` are candidates
for all pixels (no support boxes involved). With ``block=B`` the image is cut into
``B x B`` pixel blocks and each block only sees the surfels whose support box touches
it (same results, far less memory; used by the benchmark).
"""
from __future__ import annotations

import torch
from torch import Tensor

from pipeline.rasterizer.project import ALPHA_MAX, ALPHA_MIN, RHO_CUT_MAX, T_MIN, UV_MAX, Projected
from pipeline.rasterizer.types import Camera

def _composite(x: Tensor, y: Tensor, T: Tensor, o: Tensor, n: Tensor, f: Tensor, camera: Camera) -> list[Tensor]:
    """Render pixels ``(x, y)`` (each ``(N,)``) from front-to-back sorted surfels.

    Returns ``[features (N, C), alpha, depth_sum, normal (N, 3), median, distortion]``.
    """
    Tu, Tv, Tw = T[None, :, 0, :], T[None, :, 1, :], T[None, :, 2, :]  # (1, P, 3)
    k_plane = x[:, None, None] * Tw - Tu  # (N, P, 3): planes k = x T_w - T_u, l = y T_w - T_v in uv-space
    l_plane = y[:, None, None] * Tw - Tv
    q = torch.linalg.cross(k_plane, l_plane, dim=-1)  # homogeneous (u, v, 1) of the intersection
    q0, q1, q2 = q.unbind(-1)
    parallel = q2.abs() * UV_MAX <= torch.maximum(q0.abs(), q1.abs())
    q2s = torch.where(parallel, torch.ones_like(q2), q2)
    u = torch.where(parallel, torch.zeros_like(q0), q0) / q2s
    v = torch.where(parallel, torch.zeros_like(q1), q1) / q2s
    rho3 = torch.where(parallel, torch.full_like(u, float("inf")), u * u + v * v)
    c = T[:, :2, 2] / T[:, 2:3, 2]  # projected centres (P, 2); candidates have z >= near
    rho2 = 2.0 * ((x[:, None] - c[None, :, 0]) ** 2 + (y[:, None] - c[None, :, 1]) ** 2)
    use3 = rho3 <= rho2
    rho = torch.where(use3, rho3, rho2)
    # Depth of the intersection, or of the centre where the low-pass term wins (2DGS).
    z = torch.where(use3, u * Tw[..., 0] + v * Tw[..., 1] + Tw[..., 2], Tw[..., 2].expand_as(u))

    alpha = torch.clamp_max(o[None, :] * torch.exp(-0.5 * rho), ALPHA_MAX)
    keep = (z >= camera.near) & (alpha >= ALPHA_MIN) & (rho <= RHO_CUT_MAX)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    keep = keep & (torch.cumprod(1.0 - alpha, dim=1) >= T_MIN)  # the stop rule
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))

    one_minus = 1.0 - alpha
    T_before = torch.cumprod(torch.cat([torch.ones_like(x)[:, None], one_minus[:, :-1]], dim=1), dim=1)
    T_before = T_before[:, : alpha.shape[1]]
    w = alpha * T_before
    features = w @ f
    alpha_out = 1.0 - torch.prod(one_minus, dim=1)
    depth_sum = (w * z).sum(1)
    normal = w @ n

    at_median = keep & (T_before > 0.5)
    count = torch.cumsum(at_median.long(), 1)
    is_last = at_median & (count == at_median.sum(1, keepdim=True))
    median = (z * is_last).sum(1)

    # 2DGS distortion, constant-time form: sum_i w_i (m_i^2 A_i + M2_i - 2 m_i M1_i).
    near, far = camera.near, camera.far
    m = far / (far - near) * (1.0 - near / torch.where(keep, z, torch.full_like(z, near)))
    wm, wm2 = w * m, w * m * m
    M1 = torch.cumsum(wm, 1) - wm
    M2 = torch.cumsum(wm2, 1) - wm2
    distortion = (w * (m * m * (1.0 - T_before) + M2 - 2.0 * m * M1)).sum(1)
    return [features, alpha_out, depth_sum, normal, median, distortion]


def render(proj: Projected, camera: Camera, block: int | None = None) -> list[Tensor]:
    """Raw maps ``[features (H,W,C), alpha, depth_sum, normal_cam (H,W,3), median, distortion]``."""
    H, W = camera.height, camera.width
    dtype = proj.T.dtype
    if block is None:
        cand = torch.nonzero(proj.in_depth_range).flatten()
        cand = cand[torch.argsort(proj.depth[cand], stable=True)]
        ys, xs = torch.meshgrid(torch.arange(H, dtype=dtype), torch.arange(W, dtype=dtype), indexing="ij")
        outs = _composite(
            xs.flatten(), ys.flatten(), proj.T[cand], proj.opacities[cand], proj.normals_cam[cand],
            proj.colors[cand], camera,
        )
        return [t.reshape((H, W) + t.shape[1:]) for t in outs]

    order = proj.order
    box = proj.box[order]
    pieces: list[list[Tensor]] = []
    pixel_ids: list[Tensor] = []
    for y0 in range(0, H, block):
        for x0 in range(0, W, block):
            y1, x1 = min(y0 + block, H), min(x0 + block, W)
            hit = (box[:, 0] < x1) & (box[:, 1] >= x0) & (box[:, 2] < y1) & (box[:, 3] >= y0)
            cand = order[hit]
            ys, xs = torch.meshgrid(
                torch.arange(y0, y1, dtype=dtype), torch.arange(x0, x1, dtype=dtype), indexing="ij"
            )
            pieces.append(
                _composite(
                    xs.flatten(), ys.flatten(), proj.T[cand], proj.opacities[cand], proj.normals_cam[cand],
                    proj.colors[cand], camera,
                )
            )
            pixel_ids.append((ys.long() * W + xs.long()).flatten())
    inverse = torch.argsort(torch.cat(pixel_ids))
    return [torch.cat(parts)[inverse].reshape((H, W) + parts[0].shape[1:]) for parts in zip(*pieces)]
