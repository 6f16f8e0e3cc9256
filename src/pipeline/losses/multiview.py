"""PGSR multi-view consistency (Chen et al. 2024, "PGSR: Planar-based Gaussian Splatting",
Sec. 3.3): a photometric term (NCC of plane-induced homography patches between the
reference image and its source images) and a geometric term (forward-backward
reprojection error of the rendered depths). Differentiable torch functions in the rendered
reference ``depth`` and ``normal``; float32 or float64; torch/numpy only.

Conventions (``pipeline.geometry``): pixel centres at integer coordinates (pixel ``(x, y)``
is column x, row y; an image of width W spans ``[-0.5, W - 0.5)``); OpenCV camera axes
(x right, y down, z forward); depth is camera-frame z, not ray length; ``ref_to_src`` maps
the reference camera frame to a source camera frame. A rendered normal lives in the
reference camera frame and faces the camera (``n . X < 0``).

Two resolutions: depth and normal are rendered at the *training* resolution ``(h, w)``
with intrinsics ``K_train``; the images are at the *full* resolution ``(H, W)`` with
``K_full = S @ K_train``, ``S = [[sx, 0, sx/2 - 1/2], [0, sy, sy/2 - 1/2], [0, 0, 1]]``,
``sx = W / w``, ``sy = H / h`` (so ``x_full = sx (x_train + 0.5) - 0.5``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from pipeline.losses import _mv_kernels

# Added under the square root of the NCC denominator (PGSR's value; grey in [0, 1]).
NCC_EPS = 1e-8
# Camera-frame z, |rho| and homogeneous w below which a point counts as behind a camera /
# a plane counts as through the camera centre. Divisions by such values are replaced by
# divisions by 1 (the pair is invalid anyway): a masked-out 1/0 would still make the
# backward pass produce 0 * inf = NaN.
MIN_Z = 1e-6


@dataclass
class SourceView:
    """One source view of the reference.

    Attributes:
        K_full: ``(3, 3)`` intrinsics of ``grey_full`` (pixels).
        ref_to_src: ``(4, 4)`` rigid map reference camera frame -> this camera's frame.
        grey_full: ``(H_s, W_s)`` grey image in [0, 1] at full resolution.
        depth_train: ``(h_s, w_s)`` this view's rendered camera-frame depth (0 = no depth),
            used detached for the forward-backward check; ``None``: no check.
        K_train: ``(3, 3)`` intrinsics of ``depth_train``; required with it.
    """

    K_full: torch.Tensor
    ref_to_src: torch.Tensor
    grey_full: torch.Tensor
    depth_train: torch.Tensor | None = None
    K_train: torch.Tensor | None = None


def _as(x, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(x, dtype=like.dtype, device=like.device)


def _check_shape(name: str, x, shape: tuple[int, ...]) -> None:
    if not torch.is_tensor(x) or tuple(x.shape) != shape:
        got = tuple(x.shape) if torch.is_tensor(x) else type(x).__name__
        raise ValueError(f"{name} must be a tensor of shape {shape}, got {got}")


def _homographies(K_ref_inv: torch.Tensor, K_src: torch.Tensor, R: torch.Tensor, t: torch.Tensor,
                  n_over_rho: torch.Tensor) -> torch.Tensor:
    """``(M, 3, 3)``: ``K_src (R + t m^T) K_ref^-1`` for each row m of ``n_over_rho`` (M, 3).

    For X on the plane ``n . X = rho``: ``R X + t = R X + t (n . X) / rho = (R + t n^T / rho) X``.
    Formed as ``K_src R K_ref^-1 + (K_src t) (K_ref^-T m)^T``: one constant matrix plus an
    outer product per plane (no batched 3 x 3 products).
    """
    C = K_src @ R @ K_ref_inv
    u = K_src @ t
    v = n_over_rho @ K_ref_inv  # rows m^T K_ref^-1
    return C.unsqueeze(0) + u.view(1, 3, 1) * v.unsqueeze(1)


def plane_homographies(K_ref, K_src, ref_to_src, normals, points) -> torch.Tensor:
    """Plane-induced homographies from reference pixels to source pixels.

    Args:
        K_ref, K_src: ``(3, 3)`` intrinsics (pixels, integer pixel centres).
        ref_to_src: ``(4, 4)`` reference camera frame -> source camera frame ``[R | t]``.
        normals: ``(M, 3)`` plane normals in the reference camera frame (unit; the
            homography is invariant to their scale).
        points: ``(M, 3)`` a point X of each plane, reference camera frame.

    Returns ``(M, 3, 3)`` matrices ``H = K_src (R + t n^T / rho) K_ref^-1`` with
    ``rho = n . X``: ``H (u, v, 1)`` is, up to scale, the source pixel of the point where
    the ray of reference pixel ``(u, v)`` meets the plane. A plane through the reference
    camera centre (``rho = 0``) has none (non-finite entries).
    """
    if not torch.is_tensor(normals) or normals.ndim != 2 or normals.shape[1] != 3:
        raise ValueError(f"normals must be an (M, 3) tensor, got {getattr(normals, 'shape', type(normals))}")
    _check_shape("points", points, tuple(normals.shape))
    for name, m, shape in (("K_ref", K_ref, (3, 3)), ("K_src", K_src, (3, 3)), ("ref_to_src", ref_to_src, (4, 4))):
        _check_shape(name, m, shape)
    T = _as(ref_to_src, normals)
    rho = (normals * _as(points, normals)).sum(-1, keepdim=True)
    return _homographies(torch.linalg.inv(_as(K_ref, normals)), _as(K_src, normals), T[:3, :3], T[:3, 3], normals / rho)


def _sample_grey(img: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of an ``(H, W)`` image at pixel positions ``pos (..., 2)`` as (x, y).

    ``align_corners=True`` puts grid -1 / +1 on the centres of the first / last pixel, so
    ``x -> 2 x / (W - 1) - 1`` maps integer pixel centres exactly. Positions must lie in
    ``[0, W - 1] x [0, H - 1]`` for a true bilinear value (callers mask the others).
    """
    H, W = img.shape
    gx = pos[..., 0] * (2.0 / max(W - 1, 1)) - 1.0
    gy = pos[..., 1] * (2.0 / max(H - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], -1).reshape(1, 1, -1, 2)
    out = F.grid_sample(img[None, None], grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(pos.shape[:-1])


def _sample_depth(D: torch.Tensor, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth of map ``D (h, w)`` (0 = none) at pixel positions ``p (M, 2)``.

    Bilinear where ``p`` lies in ``[0, w-1] x [0, h-1]`` and all four neighbours have
    depth (differentiable in ``p``); otherwise the nearest pixel (``floor(p + 0.5)``) if
    it is in the map and has depth: an edge of the depth map must not be blended with
    "no depth" 0s. Returns ``(depth (M,), ok (M,) bool)``; depth is 0 where not ok.
    """
    h, w = D.shape
    px, py = p[:, 0], p[:, 1]
    in_near = (px >= -0.5) & (px < w - 0.5) & (py >= -0.5) & (py < h - 0.5)
    in_bil = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)
    # Far-away or huge positions would overflow the integer conversion: park them at 0.
    pxs = torch.where(in_near, px, torch.zeros_like(px))
    pys = torch.where(in_near, py, torch.zeros_like(py))
    x0 = torch.floor(pxs.detach()).clamp(0, w - 1).long()
    y0 = torch.floor(pys.detach()).clamp(0, h - 1).long()
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    fx, fy = pxs - x0.to(p.dtype), pys - y0.to(p.dtype)
    d00, d10, d01, d11 = D[y0, x0], D[y0, x1], D[y1, x0], D[y1, x1]
    bil_ok = in_bil & (d00 > 0) & (d10 > 0) & (d01 > 0) & (d11 > 0)
    bil = (1 - fy) * ((1 - fx) * d00 + fx * d10) + fy * ((1 - fx) * d01 + fx * d11)
    xn = torch.floor(pxs.detach() + 0.5).clamp(0, w - 1).long()
    yn = torch.floor(pys.detach() + 0.5).clamp(0, h - 1).long()
    dn = D[yn, xn]
    near_ok = in_near & (dn > 0)
    ok = bil_ok | near_ok
    d = torch.where(bil_ok, bil, torch.where(near_ok, dn, torch.zeros_like(dn)))
    return d, ok


def _scale_matrix(h: int, w: int, H: int, W: int, like: torch.Tensor) -> torch.Tensor:
    sx, sy = W / w, H / h
    return _as([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]], like)


def _check_reference(grey_ref_full, patch) -> None:
    if not torch.is_tensor(grey_ref_full) or grey_ref_full.ndim != 2:
        raise ValueError(f"grey_ref_full must be an (H, W) tensor, got {getattr(grey_ref_full, 'shape', type(grey_ref_full))}")
    if not isinstance(patch, int) or patch < 1 or patch % 2 == 0:
        raise ValueError(f"patch must be an odd positive int, got {patch!r}")


def _validate(depth, normal, pixels, K_train, K_full, grey_ref_full, sources, patch, ncc_gamma) -> None:
    if not torch.is_tensor(depth) or depth.ndim != 2 or not depth.is_floating_point():
        raise ValueError(f"depth must be a float (h, w) tensor, got {getattr(depth, 'shape', type(depth))}")
    h, w = depth.shape
    _check_shape("normal", normal, (h, w, 3))
    if not torch.is_tensor(pixels) or pixels.ndim != 2 or pixels.shape[1] != 2:
        raise ValueError(f"pixels must be an (M, 2) tensor of (x, y), got {getattr(pixels, 'shape', type(pixels))}")
    if pixels.is_floating_point() or pixels.is_complex() or pixels.dtype == torch.bool:
        raise ValueError(f"pixels must be an integer tensor, got {pixels.dtype}")
    if len(pixels) and (
        pixels[:, 0].min() < 0 or pixels[:, 0].max() >= w or pixels[:, 1].min() < 0 or pixels[:, 1].max() >= h
    ):
        raise ValueError(f"pixels must lie in the (h, w) = {(h, w)} training image (x in [0, w), y in [0, h))")
    _check_shape("K_train", K_train, (3, 3))
    _check_shape("K_full", K_full, (3, 3))
    _check_reference(grey_ref_full, patch)
    # A K_full that is not S @ K_train would silently put the patches in the wrong place.
    H, W = grey_ref_full.shape
    expect = _scale_matrix(h, w, H, W, K_train.double()) @ K_train.double()
    if not torch.allclose(K_full.double(), expect, rtol=0.0, atol=1e-4 * float(expect.abs().max())):
        raise ValueError(
            f"K_full must equal S @ K_train for the training size {(h, w)} and image size {(H, W)}, "
            f"i.e. {expect.tolist()}, got {K_full.tolist()}"
        )
    if not (isinstance(ncc_gamma, (int, float)) and math.isfinite(ncc_gamma) and ncc_gamma >= 0):
        raise ValueError(f"ncc_gamma must be a finite number >= 0 (0: plain NCC), got {ncc_gamma!r}")
    for i, src in enumerate(sources):
        _check_shape(f"sources[{i}].K_full", src.K_full, (3, 3))
        _check_shape(f"sources[{i}].ref_to_src", src.ref_to_src, (4, 4))
        if not torch.is_tensor(src.grey_full) or src.grey_full.ndim != 2:
            raise ValueError(f"sources[{i}].grey_full must be an (H, W) tensor")
        if (src.depth_train is None) != (src.K_train is None):
            raise ValueError(f"sources[{i}].depth_train and sources[{i}].K_train must be given together")
        if src.depth_train is not None:
            if not torch.is_tensor(src.depth_train) or src.depth_train.ndim != 2:
                raise ValueError(f"sources[{i}].depth_train must be an (h, w) tensor")
            _check_shape(f"sources[{i}].K_train", src.K_train, (3, 3))


@dataclass
class _ReferencePatches:
    """The reference side shared by both consistency measures: the sampled pixels' points
    ``X`` (training camera frame) and planes (``n / rho``), and their full-resolution
    patches (centred grey ``a_c``, variance ``var_a``, positions ``ref_pos`` (M, P, 2) as
    (x, y); ``weight`` (M, P): support weights summing to 1 per patch, ``None``: uniform)."""

    Kt: torch.Tensor
    Kf_inv: torch.Tensor
    pix: torch.Tensor
    X: torch.Tensor
    n_over_rho: torch.Tensor
    a_c: torch.Tensor
    var_a: torch.Tensor
    ok: torch.Tensor
    ref_pos: torch.Tensor
    weight: torch.Tensor | None


def _patch_moments(grey_ref: torch.Tensor, pix: torch.Tensor, sx: float, sy: float, patch: int,
                   ncc_gamma: float, kernel: str = "auto"):
    """The full-resolution reference patches of training pixels ``pix`` (M, 2) as (x, y):
    positions ``ref_pos`` (M, P, 2), ``inside`` (M,) the whole patch in the image, centred grey
    ``a_c`` (M, P), variance ``var_a`` (M,) and support ``weight`` (M, P) or ``None``. They
    depend on the image alone, not on the rendered surface, and carry no gradient.
    ``kernel`` as :func:`_warp_ncc`'s (``fused``: :func:`_mv_kernels.patch_moments`)."""
    if _fused(kernel, grey_ref):
        g, q = grey_ref.detach().contiguous().numpy(), pix.detach().to(grey_ref.dtype).contiguous().numpy()
        M, P = q.shape[0], patch * patch
        ref_pos, inside = np.empty((M, P, 2), g.dtype), np.empty(M, np.bool_)
        a_c, var_a, weight = np.empty((M, P), g.dtype), np.empty(M, g.dtype), np.empty((M, P), g.dtype)
        _mv_kernels.patch_moments(g, q, float(sx), float(sy), patch, float(ncc_gamma), ref_pos, inside, a_c, var_a, weight)
        out = [torch.from_numpy(x) for x in (ref_pos, inside, a_c, var_a)]
        return (*out, torch.from_numpy(weight) if ncc_gamma > 0 else None)
    H, W = grey_ref.shape
    # Offsets (dx, dy), row-major over dy.
    r = patch // 2
    o = torch.arange(-r, r + 1, dtype=pix.dtype, device=pix.device)
    offsets = torch.stack(torch.meshgrid(o, o, indexing="xy"), -1).reshape(-1, 2)  # (P, 2) as (x, y)
    centre = torch.stack([sx * (pix[:, 0] + 0.5) - 0.5, sy * (pix[:, 1] + 0.5) - 0.5], -1)
    ref_pos = centre.unsqueeze(1) + offsets.unsqueeze(0)  # (M, P, 2)
    inside = ((ref_pos[..., 0] >= 0) & (ref_pos[..., 0] <= W - 1)
              & (ref_pos[..., 1] >= 0) & (ref_pos[..., 1] <= H - 1)).all(-1)
    a = _sample_grey(grey_ref, ref_pos)
    weight = None
    if ncc_gamma > 0:
        # Adaptive support (Yoon & Kweon 2006): patch pixels whose grey differs from the
        # centre's count less, so a patch across a depth edge is judged by the centre's side.
        centre_grey = a[:, offsets.shape[0] // 2].unsqueeze(1)
        weight = torch.exp(-(a - centre_grey).abs() / ncc_gamma)
        weight = weight / weight.sum(-1, keepdim=True)
        a_c = a - (weight * a).sum(-1, keepdim=True)
        var_a = (weight * a_c * a_c).sum(-1)
    else:
        a_c = a - a.mean(-1, keepdim=True)
        var_a = (a_c * a_c).mean(-1)
    return ref_pos, inside, a_c, var_a, weight


def textured_pixels(grey_ref_full: torch.Tensor, h: int, w: int, patch: int, min_patch_std: float,
                    ncc_gamma: float, dtype: torch.dtype = torch.float32, chunk: int = 65536,
                    kernel: str = "auto") -> torch.Tensor:
    """The ``(h, w)`` bool mask of the training pixels whose full-resolution reference patch
    lies inside ``grey_ref_full`` and has a grey std of at least ``min_patch_std``: the only
    pixels where :func:`multiview_consistency` can have a valid pair. The same moments it
    computes (in ``dtype``, the rendered depth's), so sampling L_mv's points among these
    pixels drops only pairs that would have been invalid. Depends on the image alone: compute
    it once per view and training size. ``kernel`` as :func:`multiview_consistency`'s;
    ``chunk``: pixels per pass of the torch composition (the kernel needs no chunks)."""
    _check_reference(grey_ref_full, patch)
    _check_kernel(kernel, grey_ref_full)
    H, W = grey_ref_full.shape
    grey = grey_ref_full.to(dtype).detach()
    if _fused(kernel, grey):
        out = np.empty((h, w), np.bool_)
        _mv_kernels.textured_grid(grey.contiguous().numpy(), h, w, patch, float(ncc_gamma), float(min_patch_std), out)
        return torch.from_numpy(out)
    dev = grey_ref_full.device
    ys, xs = torch.meshgrid(torch.arange(h, device=dev), torch.arange(w, device=dev), indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1).to(dtype)
    out = torch.empty(len(pix), dtype=torch.bool, device=dev)
    for start in range(0, len(pix), chunk):
        part = pix[start:start + chunk]
        _, inside, _, var_a, _ = _patch_moments(grey, part, W / w, H / h, patch, ncc_gamma, kernel)
        out[start:start + chunk] = inside & (var_a.sqrt() >= min_patch_std)
    return out.reshape(h, w)


def _reference_patches(depth, normal, pixels, K_train, K_full, grey_ref_full, patch, min_patch_std,
                       ncc_gamma, kernel) -> _ReferencePatches:
    h, w = depth.shape
    Kt, Kf = _as(K_train, depth), _as(K_full, depth)
    grey_ref = _as(grey_ref_full, depth).detach()
    H, W = grey_ref.shape
    sx, sy = W / w, H / h
    xs, ys = pixels[:, 0].long().to(depth.device), pixels[:, 1].long().to(depth.device)
    z = depth[ys, xs]
    n = F.normalize(normal[ys, xs].to(depth.dtype), dim=-1)
    pix = torch.stack([xs, ys], -1).to(depth.dtype)
    pix_h = torch.cat([pix, torch.ones_like(pix[:, :1])], -1)
    X = (pix_h @ torch.linalg.inv(Kt).t()) * z.unsqueeze(1)  # rays with z = 1, times depth
    rho = (n * X).sum(-1)
    rho_ok = rho.abs() > MIN_Z
    n_over_rho = n / torch.where(rho_ok, rho, torch.ones_like(rho)).unsqueeze(1)

    ref_pos, ref_inside, a_c, var_a, weight = _patch_moments(grey_ref, pix, sx, sy, patch, ncc_gamma, kernel)
    ok = (z.detach() > MIN_Z) & rho_ok.detach() & ref_inside & (var_a.sqrt() >= min_patch_std)
    return _ReferencePatches(Kt, torch.linalg.inv(Kf), pix, X, n_over_rho, a_c, var_a, ok, ref_pos, weight)


def _warp_into(ref: _ReferencePatches, src: SourceView, like: torch.Tensor):
    """The reference patches warped into ``src`` through their planes. Returns ``(R, t,
    pos (M, P, 2) source pixels, Xs (M, 3) points in the source frame, front (M,),
    valid (M,))``, valid: reference patch usable, point in front of the source, every
    warped patch point in front of it and inside its image."""
    T = _as(src.ref_to_src, like)
    R, t = T[:3, :3], T[:3, 3]
    Hs, Ws = src.grey_full.shape
    Hm = _homographies(ref.Kf_inv, _as(src.K_full, like), R, t, ref.n_over_rho)
    ref_h = torch.cat([ref.ref_pos, torch.ones_like(ref.ref_pos[..., :1])], -1)  # (M, P, 3)
    uvw = torch.einsum("mij,mpj->mpi", Hm, ref_h)
    wz = uvw[..., 2]
    w_pos = wz > MIN_Z
    pos = uvw[..., :2] / torch.where(w_pos, wz, torch.ones_like(wz)).unsqueeze(-1)
    Xs = ref.X @ R.t() + t
    front = Xs[:, 2] > MIN_Z
    pd = pos.detach()
    inside = ((pd[..., 0] >= 0) & (pd[..., 0] <= Ws - 1) & (pd[..., 1] >= 0) & (pd[..., 1] <= Hs - 1)).all(-1)
    return R, t, pos, Xs, front, ref.ok & front & w_pos.all(-1) & inside


def _source_depth_at(Xs: torch.Tensor, front: torch.Tensor, src: SourceView, like: torch.Tensor):
    """Where the points ``Xs`` (source camera frame) project into ``src``'s training pixels
    and the source's rendered depth there (:func:`_sample_depth`, detached). Returns ``(p
    (M, 2), zs (M,) the points' depths, 1 where not in front, d_src (M,), d_ok (M,))``."""
    zs = torch.where(front, Xs[:, 2], torch.ones_like(Xs[:, 2]))
    p = (Xs @ _as(src.K_train, like).t())[:, :2] / zs.unsqueeze(1)
    d_src, d_ok = _sample_depth(_as(src.depth_train, like).detach(), p)
    return p, zs, d_src, d_ok


def _ncc(ref: _ReferencePatches, grey: torch.Tensor, pos: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    # Invalid pairs sample at (0, 0): finite values, and their gradient is masked by the callers.
    b = _sample_grey(grey, torch.where(valid.view(-1, 1, 1), pos, torch.zeros_like(pos)))
    w = ref.weight
    if w is None:
        b_c = b - b.mean(-1, keepdim=True)
        cov = (ref.a_c * b_c).mean(-1)
        return cov / torch.sqrt(ref.var_a * (b_c * b_c).mean(-1) + NCC_EPS)
    b_c = b - (w * b).sum(-1, keepdim=True)
    cov = (w * ref.a_c * b_c).sum(-1)
    return cov / torch.sqrt(ref.var_a * (w * b_c * b_c).sum(-1) + NCC_EPS)


class _WarpNCC(torch.autograd.Function):
    """NCC of each reference patch warped into a source through ``Hm (M, 3, 3)`` and whether
    the warped patch is inside it, differentiable in ``Hm``: the fused CPU kernels of
    :mod:`pipeline.losses._mv_kernels` (``_warp_into`` + ``_ncc`` is their reference)."""

    @staticmethod
    def forward(ctx, Hm, ref_pos, grey, a_c, var_a, weight, usable):
        arrays = [x.detach().contiguous().numpy() for x in (Hm, ref_pos, grey, a_c, var_a, weight)]
        M, P = a_c.shape
        ncc, inside = np.empty(M, arrays[0].dtype), np.empty(M, np.bool_)
        _mv_kernels.warp_ncc_forward(*arrays, usable.contiguous().numpy(), NCC_EPS, MIN_Z, ncc, inside,
                           np.empty((M, P), arrays[0].dtype))
        ctx.arrays, ctx.inside = arrays, inside
        inside_t = torch.from_numpy(inside)
        ctx.mark_non_differentiable(inside_t)
        return torch.from_numpy(ncc), inside_t

    @staticmethod
    def backward(ctx, grad_ncc, _grad_inside):
        Hm, ref_pos, grey, a_c, var_a, weight = ctx.arrays
        grad_H = np.empty_like(Hm)
        _mv_kernels.warp_ncc_backward(Hm, ref_pos, grey, a_c, var_a, weight, ctx.inside, NCC_EPS, MIN_Z,
                            grad_ncc.detach().contiguous().numpy(), grad_H, np.empty(a_c.shape + (6,), a_c.dtype))
        return torch.from_numpy(grad_H), None, None, None, None, None, None


KERNELS = ("auto", "fused", "torch")


def _check_kernel(kernel: str, like: torch.Tensor) -> None:
    if kernel not in KERNELS or (kernel == "fused" and like.device.type != "cpu"):
        raise ValueError(f"kernel must be one of {KERNELS} ('fused' on CPU tensors only), got {kernel!r} "
                         f"for {like.device.type} tensors")


def _fused(kernel: str, like: torch.Tensor) -> bool:
    """Whether ``kernel`` (checked by :func:`_check_kernel`) runs the numba kernels for
    tensors like ``like``: ``fused``, or ``auto`` on the CPU."""
    return kernel == "fused" or (kernel == "auto" and like.device.type == "cpu")


def _warp_ncc(ref: _ReferencePatches, src: SourceView, like: torch.Tensor, kernel: str):
    """The reference patches warped into ``src`` and their NCC there: ``(R, t, Xs, front,
    valid, ncc)`` as :func:`_warp_into` and :func:`_ncc` give them. ``kernel``: ``torch``
    composes them in torch (the reference; any device), ``fused`` runs the numba kernels
    (CPU), ``auto`` the fused ones on CPU tensors."""
    if not _fused(kernel, like):
        R, t, pos, Xs, front, valid = _warp_into(ref, src, like)
        return R, t, Xs, front, valid, _ncc(ref, _as(src.grey_full, like).detach(), pos, valid)
    T = _as(src.ref_to_src, like)
    R, t = T[:3, :3], T[:3, 3]
    Hm = _homographies(ref.Kf_inv, _as(src.K_full, like), R, t, ref.n_over_rho)
    Xs = ref.X @ R.t() + t
    front = Xs[:, 2] > MIN_Z
    usable = ref.ok & front
    M, P = ref.a_c.shape
    weight = ref.weight if ref.weight is not None else torch.full((M, P), 1.0 / P, dtype=like.dtype)
    ncc, inside = _WarpNCC.apply(Hm, ref.ref_pos, _as(src.grey_full, like).detach(), ref.a_c.detach(),
                                 ref.var_a.detach(), weight.detach(), usable.detach())
    return R, t, Xs, front, usable & inside, ncc


def reference_pixels(surface: torch.Tensor, normal: torch.Tensor, K_train: torch.Tensor,
                     max_incidence_deg: float) -> torch.Tensor:
    """The ``(h, w)`` bool mask of the ``surface`` pixels whose rendered normal is within
    ``max_incidence_deg`` of the ray back to the camera: L_mv's reference pixels.

    ``surface`` (h, w) bool: the rendered surface at the training size; ``normal`` (h, w, 3)
    its camera-frame normals (any length, either sign); ``K_train`` their intrinsics (integer
    pixel centres). At grazing incidence the plane's homography swings with the smallest tilt
    and the patch is the object's rim, where the views see different silhouettes: on
    synth_textureless, L_mv from every pixel pulled the dome's rim behind the truth
    (docs/optimize.md)."""
    if max_incidence_deg >= 90.0:
        return surface.clone()
    h, w = surface.shape
    n = normal.detach()
    ys, xs = torch.meshgrid(torch.arange(h, dtype=n.dtype), torch.arange(w, dtype=n.dtype), indexing="ij")
    Kinv = torch.linalg.inv(_as(K_train, n))
    rays = [Kinv[i, 0] * xs + Kinv[i, 1] * ys + Kinv[i, 2] for i in range(3)]
    # Channel by channel (a sum over an axis of 3 is slow in torch here); a zero normal has
    # cosine 0, as F.normalize would give it.
    dot = (n[..., 0] * rays[0] + n[..., 1] * rays[1] + n[..., 2] * rays[2]).abs()
    n_len = torch.sqrt(n[..., 0] * n[..., 0] + n[..., 1] * n[..., 1] + n[..., 2] * n[..., 2])
    ray_len = torch.sqrt(rays[0] * rays[0] + rays[1] * rays[1] + rays[2] * rays[2])
    cos = dot / (n_len.clamp_min(1e-12) * ray_len.clamp_min(1e-12))
    return surface & (cos >= math.cos(math.radians(max_incidence_deg)))


def multiview_consistency(
    depth: torch.Tensor,
    normal: torch.Tensor,
    pixels: torch.Tensor,
    K_train: torch.Tensor,
    K_full: torch.Tensor,
    grey_ref_full: torch.Tensor,
    sources: list[SourceView],
    patch: int = 7,
    min_patch_std: float = 0.01,
    max_fb_px: float = 1.0,
    ncc_gamma: float = 0.0,
    best_sources: int = 0,
    max_cost: float = 2.0,
    kernel: str = "auto",
) -> dict[str, torch.Tensor]:
    """PGSR's multi-view photometric and geometric consistency of one reference view.

    Each pixel ``(x, y)`` of ``pixels`` defines a point ``X = depth[y, x] K_train^-1 (x, y, 1)``
    and a plane through it with the normalised ``normal[y, x]`` (``rho = n . X``). Its
    reference patch is the ``patch x patch`` grid of integer full-resolution offsets around
    ``u = (sx (x + 0.5) - 0.5, sy (y + 0.5) - 0.5)``, sampled bilinearly in ``grey_ref_full``
    (constants). For each source the plane's homography (:func:`plane_homographies` with
    ``K_full`` and ``src.K_full``) warps the patch into ``src.grey_full`` (bilinear; the
    gradient reaches depth and normal through the warped positions), and the cost is
    ``clamp(1 - NCC, 0, 2)``, ``NCC = cov / sqrt(var_ref var_src + 1e-8)`` (population
    moments over the patch; with ``ncc_gamma > 0`` weighted moments, each patch pixel
    weighted by ``exp(-|a - a_centre| / ncc_gamma)`` of its reference grey ``a``, normalised
    to sum 1: adaptive support weights, so a patch straddling a depth edge is judged by the
    pixels on the centre's side).

    A (pixel, source) pair is valid when: the depth is positive, ``|rho| > MIN_Z``, the
    reference patch lies inside ``[0, W-1] x [0, H-1]`` and its grey std is at least
    ``min_patch_std`` (flat patches have no NCC: excluded, not penalised), X is in front of
    the source (z > MIN_Z), every warped patch point has a positive homogeneous coordinate
    (its plane point is in front of the source) and lies inside the source image
    ``[0, W_s-1] x [0, H_s-1]``. For a source with ``depth_train``, also the
    forward-backward check: X is projected into the source's training pixels
    (``src.K_train``), the source depth is read there (bilinear; the nearest pixel where a
    neighbour has no depth; none: invalid), that source point is mapped back and projected
    with ``K_train``; ``phi`` = its distance in training pixels to ``(x, y)`` must be below
    ``max_fb_px`` (else occluded / inconsistent), and the pair's cost is weighted by
    ``exp(-phi)`` (phi detached). Sources without depth have weight 1 and no phi.

    Args:
        depth: ``(h, w)`` rendered camera-frame depth (scene units).
        normal: ``(h, w, 3)`` rendered normals, reference camera frame, any length.
        pixels: ``(M, 2)`` integer ``(x, y)`` training pixels to use.
        K_train, K_full: ``(3, 3)`` reference intrinsics at ``(h, w)`` and at the size of
            ``grey_ref_full``; ``K_full`` must be ``S @ K_train`` (ValueError otherwise).
        grey_ref_full: ``(H, W)`` reference grey image in [0, 1].
        sources: the source views (:class:`SourceView`).
        patch: odd patch side in full-resolution pixels.
        min_patch_std: least reference-patch grey std for a pair to count.
        max_fb_px: forward-backward reprojection error (training pixels) at which a pair
            becomes invalid.
        ncc_gamma: grey scale of the adaptive support weights (0: plain NCC, PGSR's).
        best_sources: > 0: of each pixel's valid pairs only the ``best_sources`` of lowest
            cost count (ties by source order), in both terms; 0: all (PGSR's).
        max_cost: pairs whose cost exceeds it are invalid (2: none is).
        kernel: how the patches are warped and compared: ``fused`` numba kernels (CPU
            tensors), ``torch`` (any device; their reference), ``auto`` fused on CPU.

    Returns ``{"photo": sum of exp(-phi) cost over valid pairs / number of valid pairs,
    "geo": mean phi over valid pairs with the check (training pixels),
    "valid_fraction": valid pairs / (M * len(sources)) (detached)}``; a term with no pair
    is a zero that is connected to ``depth`` and ``normal`` (zero gradients).
    """
    _validate(depth, normal, pixels, K_train, K_full, grey_ref_full, sources, patch, ncc_gamma)
    _check_kernel(kernel, depth)
    M = len(pixels)

    # A zero that carries depth's and normal's graph with exactly zero gradients
    # (torch.where sends nothing to the branch it does not take).
    zero = (torch.where(torch.zeros_like(depth, dtype=torch.bool), depth, 0.0).sum()
            + torch.where(torch.zeros_like(normal, dtype=torch.bool), normal, 0.0).sum())
    ref = _reference_patches(depth, normal, pixels, K_train, K_full, grey_ref_full, patch, min_patch_std, ncc_gamma, kernel)
    Kt, pix = ref.Kt, ref.pix

    costs, weights, valids, phis, checked = [], [], [], [], []
    for src in sources:
        R, t, Xs, front, valid, ncc = _warp_ncc(ref, src, depth, kernel)
        cost = (1.0 - ncc).clamp(0.0, 2.0)

        weight = torch.ones_like(cost)
        phi = torch.zeros_like(cost)
        if src.depth_train is not None:
            Ks = _as(src.K_train, depth)
            p, _, d_src, d_ok = _source_depth_at(Xs, front, src, depth)
            Ys = (torch.cat([p, torch.ones_like(p[:, :1])], -1) @ torch.linalg.inv(Ks).t()) * d_src.unsqueeze(1)
            Y = (Ys - t) @ R  # R^T (Ys - t): back into the reference frame
            q = Y @ Kt.t()
            q_ok = q[:, 2] > MIN_Z
            rep = q[:, :2] / torch.where(q_ok, q[:, 2], torch.ones_like(q[:, 2])).unsqueeze(1)
            phi = torch.linalg.vector_norm(rep - pix, dim=-1)  # its backward is 0, not NaN, at 0
            valid = valid & d_ok & q_ok & (phi.detach() < max_fb_px)
            weight = torch.exp(-phi.detach())
        costs.append(cost)
        weights.append(weight)
        valids.append(valid)
        phis.append(phi)
        checked.append(src.depth_train is not None)
    if not sources:
        return {"photo": zero, "geo": zero, "valid_fraction": torch.tensor(0.0, dtype=depth.dtype, device=depth.device)}
    cost, weight, phi, valid = torch.stack(costs), torch.stack(weights), torch.stack(phis), torch.stack(valids)
    if max_cost < 2.0:
        valid = valid & (cost.detach() <= max_cost)
    if 0 < best_sources < len(sources):
        # Each pixel keeps its best_sources lowest-cost valid pairs: a source that does not see
        # the point (occluded, yet within the forward-backward tolerance) matches worst.
        key = torch.where(valid, cost.detach(), torch.full_like(cost, math.inf))
        rank = torch.argsort(torch.argsort(key, dim=0, stable=True), dim=0, stable=True)
        valid = valid & (rank < best_sources)
    geo_valid = valid & torch.tensor(checked, device=depth.device).view(-1, 1)
    photo_sum = zero + torch.where(valid, weight * cost, torch.zeros_like(cost)).sum()
    geo_sum = zero + torch.where(geo_valid, phi, torch.zeros_like(phi)).sum()
    n_valid, n_geo = int(valid.sum()), int(geo_valid.sum())

    return {
        "photo": photo_sum / max(n_valid, 1),
        "geo": geo_sum / max(n_geo, 1),
        "valid_fraction": torch.tensor(n_valid / max(M * len(sources), 1), dtype=depth.dtype, device=depth.device),
    }


@torch.no_grad()
def best_source_ncc(
    depth: torch.Tensor,
    normal: torch.Tensor,
    pixels: torch.Tensor,
    K_train: torch.Tensor,
    K_full: torch.Tensor,
    grey_ref_full: torch.Tensor,
    sources: list[SourceView],
    patch: int = 7,
    min_patch_std: float = 0.01,
    occlusion_rel_tol: float = 0.01,
    ncc_gamma: float = 0.0,
    kernel: str = "auto",
) -> torch.Tensor:
    """Per pixel, the best NCC over the sources of the reference patch warped through the
    pixel's rendered plane: the evidence :func:`multiview_consistency` optimises, as a
    figure (no gradient).

    Same geometry and validity rules as :func:`multiview_consistency` (patch at full
    resolution, plane homography, patch inside both images, in front of the source). A
    source with ``depth_train`` is also no evidence where it does not see the point: its
    rendered depth at the point's projection (read as :func:`multiview_consistency` reads
    it) is smaller than the point's depth there by more than ``occlusion_rel_tol``
    (relative), or it has none. ``ncc_gamma`` as there (0: plain NCC). Returns ``(M,)``:
    the largest NCC in [-1, 1] over the valid sources; ``nan`` where no source is valid or
    the reference patch is flatter than ``min_patch_std`` (no evidence either way).
    ``kernel`` as there."""
    _validate(depth, normal, pixels, K_train, K_full, grey_ref_full, sources, patch, ncc_gamma)
    _check_kernel(kernel, depth)
    ref = _reference_patches(depth, normal, pixels, K_train, K_full, grey_ref_full, patch, min_patch_std, ncc_gamma, kernel)
    best = torch.full_like(ref.X[:, 2], float("nan"))
    for src in sources:
        _, _, Xs, front, valid, ncc = _warp_ncc(ref, src, depth, kernel)
        if src.depth_train is not None:
            _, zs, d_src, d_ok = _source_depth_at(Xs, front, src, depth)
            valid = valid & d_ok & (zs <= d_src * (1.0 + occlusion_rel_tol))
        best = torch.where(valid & ~(ncc <= best), ncc, best)  # ~(<=): nan best takes any valid ncc
    return best
