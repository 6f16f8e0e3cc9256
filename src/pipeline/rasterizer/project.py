"""Per-surfel set-up shared by all CPU backends (plain differentiable PyTorch).

For each surfel: the 2DGS ray transform ``T = K [s_u t_u, s_v t_v, p]`` in the camera
frame (rows ``T_u, T_v, T_w``), its camera-facing normal, its colour (SH evaluated
towards the camera), and (not differentiable) its conservative pixel support box and
the front-to-back order.

Support box: a pair contributes only if ``alpha = o G >= 1/255`` and ``rho <= 9``
(3 sigma, 2DGS's support), i.e. if ``rho = min(rho3, rho2) <= rho_cut = min(2 ln(255 o), 9)``.
The box is the union of the
image of the disc ``u^2 + v^2 <= rho_cut`` (an ellipse, bounded through the dual conic
``T diag(rho_cut, rho_cut, -1) T^T``) and the square ``|(x, y) - c| <= sqrt(rho_cut / 2)``
of the low-pass term, widened by half a pixel. It never drops a contributing pair, so
it is only an accelerator: the result equals the dense evaluation over all pixels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from pipeline.rasterizer.types import Camera, Surfels

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
# A pair farther than 3 sigma from its surfel's centre (rho > 9) is skipped, as 2DGS's and
# gsplat's kernels bound a surfel at 3 sigma; without it a surfel of opacity o reached to
# rho = 2 ln(255 o) (3.33 sigma at o = 1): 16% more pairs at 800x600 / 200k, each with
# alpha < 0.011 o.
RHO_CUT_MAX = 9.0
# Where |u| or |v| would exceed UV_MAX (rho3 > 1e12, so alpha == 0 through rho3) the ray
# counts as parallel to the splat: rho3 = inf. Shared by every backend; it keeps every
# division bounded, so unused branches never produce inf * 0 in a gradient.
UV_MAX = 1e6

SH_C0 = 0.28209479177387814  # the degree-0 real spherical harmonic, 1 / (2 sqrt(pi))
_SH_C1 = 0.4886025119029199
_SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
_SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


@dataclass
class Projected:
    """Per-surfel screen-space data (``P`` surfels, input order).

    ``T``, ``normals_cam``, ``colors``, ``opacities`` are differentiable; the rest is
    not. ``box`` is ``(xmin, xmax, ymin, ymax)`` inclusive pixel indices, valid only
    where ``visible``; ``order`` lists the visible surfels front to back (stable sort
    on the centre depth).
    """

    T: Tensor  # (P, 3, 3) rows T_u, T_v, T_w
    normals_cam: Tensor  # (P, 3)
    colors: Tensor  # (P, C)
    opacities: Tensor  # (P,)
    means2d: Tensor  # (P, 2) projected centre, pixels
    depth: Tensor  # (P,) centre camera z
    in_depth_range: Tensor  # (P,) bool: near <= z_centre <= far
    visible: Tensor  # (P,) bool: in range, opacity >= 1/255, box inside the image
    box: Tensor  # (P, 4) int64
    radii: Tensor  # (P,) int32
    order: Tensor  # (V,) int64


def quat_to_rotmat(q: Tensor) -> Tensor:
    """``(P, 4)`` wxyz quaternions (any non-zero length) -> ``(P, 3, 3)`` rotations."""
    w, x, y, z = F.normalize(q, dim=-1).unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(q.shape[:-1] + (3, 3))


def eval_sh(degree: int, sh: Tensor, dirs: Tensor) -> Tensor:
    """Real SH (3DGS sign convention) of ``(P, K, 3)`` coefficients along unit ``dirs``,
    shifted by 0.5 and clamped at 0 like 3DGS/gsplat. Returns ``(P, 3)``."""
    out = SH_C0 * sh[:, 0]
    if degree > 0:
        x, y, z = (dirs[:, i : i + 1] for i in range(3))
        out = out - _SH_C1 * y * sh[:, 1] + _SH_C1 * z * sh[:, 2] - _SH_C1 * x * sh[:, 3]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            out = (
                out
                + _SH_C2[0] * xy * sh[:, 4]
                + _SH_C2[1] * yz * sh[:, 5]
                + _SH_C2[2] * (2 * zz - xx - yy) * sh[:, 6]
                + _SH_C2[3] * xz * sh[:, 7]
                + _SH_C2[4] * (xx - yy) * sh[:, 8]
            )
            if degree > 2:
                out = (
                    out
                    + _SH_C3[0] * y * (3 * xx - yy) * sh[:, 9]
                    + _SH_C3[1] * xy * z * sh[:, 10]
                    + _SH_C3[2] * y * (4 * zz - xx - yy) * sh[:, 11]
                    + _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * sh[:, 12]
                    + _SH_C3[4] * x * (4 * zz - xx - yy) * sh[:, 13]
                    + _SH_C3[5] * z * (xx - yy) * sh[:, 14]
                    + _SH_C3[6] * x * (xx - 3 * yy) * sh[:, 15]
                )
    return torch.clamp_min(out + 0.5, 0.0)


def support_boxes(T: Tensor, opacities: Tensor, camera: Camera) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Conservative pixel boxes (see module doc). Float64, no gradient.

    Returns ``(box (P, 4) int64, radii (P,) int32, in_depth_range (P,), visible (P,))``.
    """
    T = T.detach().to(torch.float64)
    o = opacities.detach().to(torch.float64)
    W, H = camera.width, camera.height
    z = T[:, 2, 2]
    in_range = (z >= camera.near) & (z <= camera.far)
    with torch.no_grad():
        rho_cut = torch.clamp_max(2.0 * torch.log(255.0 * o), RHO_CUT_MAX)  # -inf at o = 0
        ok = in_range & (rho_cut >= 0)
        r2 = torch.where(ok, rho_cut, torch.zeros_like(rho_cut))
        Tu, Tv, Tw = T[:, 0], T[:, 1], T[:, 2]

        def dual(a: Tensor, b: Tensor) -> Tensor:  # entry of T diag(r2, r2, -1) T^T
            return r2 * (a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]) - a[:, 2] * b[:, 2]

        c22 = dual(Tw, Tw)
        # c22 < 0 <=> the disc lies in front of the camera plane, so its image is an ellipse.
        bounded = c22 < 0
        den = torch.where(bounded, c22, -torch.ones_like(c22))
        xc, yc = dual(Tu, Tw) / den, dual(Tv, Tw) / den
        hx = torch.sqrt(torch.clamp_min(xc * xc - dual(Tu, Tu) / den, 0.0))
        hy = torch.sqrt(torch.clamp_min(yc * yc - dual(Tv, Tv) / den, 0.0))
        zs = torch.where(ok, z, torch.ones_like(z))
        cx, cy = Tu[:, 2] / zs, Tv[:, 2] / zs
        d2 = torch.sqrt(r2 / 2.0)
        big = float(max(W, H)) * 4.0
        lo_x = torch.minimum(xc - hx, cx - d2)
        hi_x = torch.maximum(xc + hx, cx + d2)
        lo_y = torch.minimum(yc - hy, cy - d2)
        hi_y = torch.maximum(yc + hy, cy + d2)
        # An unbounded image (disc crossing the camera plane): the whole image.
        lo_x = torch.where(bounded, lo_x, torch.full_like(lo_x, -big)).nan_to_num(nan=-big)
        lo_y = torch.where(bounded, lo_y, torch.full_like(lo_y, -big)).nan_to_num(nan=-big)
        hi_x = torch.where(bounded, hi_x, torch.full_like(hi_x, big)).nan_to_num(nan=big)
        hi_y = torch.where(bounded, hi_y, torch.full_like(hi_y, big)).nan_to_num(nan=big)
        radius = torch.stack([hi_x - cx, cx - lo_x, hi_y - cy, cy - lo_y], 1).amax(1)
        radius = torch.ceil(radius.clamp(0, big)).nan_to_num(nan=big)
        xmin = torch.ceil(lo_x - 0.5).clamp(-1, W).long().clamp_min(0)
        xmax = torch.floor(hi_x + 0.5).clamp(-1, W).long().clamp_max(W - 1)
        ymin = torch.ceil(lo_y - 0.5).clamp(-1, H).long().clamp_min(0)
        ymax = torch.floor(hi_y + 0.5).clamp(-1, H).long().clamp_max(H - 1)
        visible = ok & (xmin <= xmax) & (ymin <= ymax)
        box = torch.stack([xmin, xmax, ymin, ymax], 1)
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
    return box, radii, in_range, visible


def colors_of(surfels: Surfels, camera: Camera) -> Tensor:
    """``(P, C)`` colours: the features, or the SH evaluated towards the camera centre."""
    if surfels.sh_degree is None:
        return surfels.features
    dirs = F.normalize(surfels.means - camera.cam_center.to(surfels.means), dim=-1)  # device and dtype
    return eval_sh(surfels.sh_degree, surfels.features, dirs)


def project(surfels: Surfels, camera: Camera, *, track_means2d: bool) -> Projected:
    """Build the per-surfel data of ``surfels`` seen by ``camera`` (see module doc).

    With ``track_means2d`` the returned ``means2d`` is a fresh leaf requiring grad that
    enters ``T`` as a zero-valued screen translation ``T <- [[1,0,dx],[0,1,dy],[0,0,1]] T``,
    so its gradient is the image-plane positional gradient of each splat.
    """
    dtype = surfels.means.dtype
    K = camera.K.to(dtype)
    Rwc = camera.world_to_cam[:3, :3].to(dtype)
    twc = camera.world_to_cam[:3, 3].to(dtype)

    R = quat_to_rotmat(surfels.quats)  # world frame, columns t_u, t_v, n
    R_cam = Rwc @ R  # broadcast (3,3) @ (P,3,3)
    p_cam = surfels.means @ Rwc.T + twc
    M = torch.stack(
        [surfels.scales[:, 0:1] * R_cam[:, :, 0], surfels.scales[:, 1:2] * R_cam[:, :, 1], p_cam], dim=-1
    )
    T = K @ M  # (P, 3, 3): T @ (u, v, 1) = homogeneous pixel of P(u, v)

    depth = p_cam[:, 2].detach()
    safe_z = torch.where(depth > 0, depth, torch.ones_like(depth))
    centre = (T[:, :2, 2].detach() / safe_z[:, None]).clone()
    if track_means2d:
        means2d = centre.requires_grad_(True)
        shift = means2d - means2d.detach()  # zero value, identity gradient
        T = T + torch.cat([shift[:, :, None] * T[:, 2:3, :], torch.zeros_like(T[:, 2:3, :])], dim=1)
    else:
        means2d = centre

    n_cam = R_cam[:, :, 2]
    # Face the camera: n <- -sign(n . p_view) n (dropped when the plane contains the eye).
    facing = -torch.sign((n_cam * p_cam).sum(-1)).detach()
    normals_cam = n_cam * facing[:, None]

    colors = colors_of(surfels, camera)

    box, radii, in_range, visible = support_boxes(T, surfels.opacities, camera)
    key = torch.where(visible, depth, torch.full_like(depth, math.inf))
    order = torch.argsort(key, stable=True)[: int(visible.sum())]
    return Projected(
        T=T,
        normals_cam=normals_cam,
        colors=colors,
        opacities=surfels.opacities,
        means2d=means2d,
        depth=depth,
        in_depth_range=in_range,
        visible=visible,
        box=box,
        radii=radii,
        order=order,
    )
