"""GCGS geometric-consistent feature loss L_gcf (Eq. 4-9, see docs/priors.md) and the
feature sampling it uses. Differentiable torch functions; float32 or float64.

Conventions: OpenCV camera axes, ``world_to_cam`` maps world (mm) to camera, pixel
centres at integer coordinates (``pipeline.geometry``). Depth maps are camera-frame z in
mm, as the 2DGS renderer gives them, in the project's "no depth" convention
(:class:`pipeline.init.io.DepthMap`): finite, 0 where there is no depth, and a bool
validity mask saying which pixels are surface points. A rendered expected depth is
positive wherever any surfel contributes, however faint its alpha, so the mask (e.g.
``alpha > 0.5``), not the depth, decides.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

# Below this a feature vector counts as zero: its cosine with anything is defined as 0.
COS_EPS = 1e-8
# Camera-frame z (mm) below which a point counts as behind a source camera.
MIN_Z_MM = 1e-6


def _t(x, like: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x, dtype=like.dtype, device=like.device)


def sample_features(feats: torch.Tensor, pix: torch.Tensor, image_size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinearly sample a feature map at image pixel positions.

    Args:
        feats: ``(C, h, w)`` features of an image of ``image_size = (H, W)``; a feature
            map at scale ``s = w / W`` has its pixel centre ``j`` at image coordinate
            ``(j + 0.5) / s - 0.5`` (integer pixel centres at both resolutions, so a
            1/2-resolution map has centre ``j`` at image ``x = 2 j + 0.5``).
        pix: ``(N, 2)`` image coordinates ``(x, y)``.

    Returns ``(values (C, N), inside (N,) bool)``; ``inside`` is False where the sample
    needs feature pixels outside the map (such values are meaningless).
    """
    C, h, w = feats.shape
    H, W = image_size
    fx = (pix[:, 0] + 0.5) * (w / W) - 0.5
    fy = (pix[:, 1] + 0.5) * (h / H) - 0.5
    inside = (fx >= 0) & (fx <= w - 1) & (fy >= 0) & (fy <= h - 1) & torch.isfinite(fx) & torch.isfinite(fy)
    # align_corners=True maps -1/+1 to the centres of the first/last feature pixel.
    gx = torch.where(inside, fx, torch.zeros_like(fx)) * (2.0 / max(w - 1, 1)) - 1.0
    gy = torch.where(inside, fy, torch.zeros_like(fy)) * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], dim=-1).view(1, 1, -1, 2)
    vals = F.grid_sample(feats.unsqueeze(0), grid, mode="bilinear", padding_mode="zeros", align_corners=True)
    return vals.view(C, -1), inside


def _nonzero(f: torch.Tensor) -> torch.Tensor:
    """``(N,)`` bool: which columns of ``(C, N)`` features are not (numerically) zero."""
    return (f * f).sum(0) > COS_EPS * COS_EPS


def cosine(a: torch.Tensor, b: torch.Tensor, dim: int = 0) -> torch.Tensor:
    """Cosine similarity along ``dim``; 0 where either vector is (numerically) zero."""
    num = (a * b).sum(dim)
    # Clamp before the square root: sqrt'(0) is infinite and would turn the zero gradient
    # of a clamped entry into NaN.
    den = torch.sqrt(((a * a).sum(dim) * (b * b).sum(dim)).clamp_min(COS_EPS * COS_EPS))
    return num / den


def gcf_loss(
    depth_ref: torch.Tensor,
    K_ref,
    world_to_cam_ref,
    feats_ref: torch.Tensor,
    sources: Sequence[tuple],
    *,
    valid: torch.Tensor | np.ndarray,
    ref_image_size: tuple[int, int] | None = None,
    max_dissimilarity: float | None = None,
    return_terms: bool = False,
):
    """Geometric-consistent feature loss L_gcf (GCGS Eq. 4-9), differentiable in depth.

    For each reference pixel p (integer centre) in ``valid``, the surface point is
    ``x = O_ref + z(p) K_ref^-1 (p, 1)`` in the camera frame, i.e. Eq. 4's
    ``O_ref + D(p) d(p)`` with the unit ray d and ``D = z |K^-1 (p, 1)|`` (``depth_ref`` is
    camera-frame z, as rendered). For each source view i: ``v_ref``, ``v_i`` are the unit
    vectors from the camera centres to x, ``w = max(0, v_ref . v_i)``, ``p_i`` the
    projection of x, and the term is ``w (1 - cos(f_ref(p), f_i(p_i)))`` with bilinear
    feature sampling (:func:`sample_features`). A point behind a source camera or
    projecting outside its feature map contributes nothing for that source.

    Three choices the paper leaves open, all so that the loss only moves depth where the
    features carry information:

    * ``w`` is a confidence and is held constant (detached). Its own depth gradient
      would reward moving every point towards the cameras (the ray angle grows, ``w``
      shrinks) whatever the features say.
    * A zero feature vector (a flat patch, :mod:`pipeline.priors.features`) has no
      cosine: a reference pixel with one (or outside its feature map: the half-pixel
      border of a 1/2-resolution map) is not a point, a source sample with one
      contributes nothing. Counted as ``1 - 0`` they would add ``w`` and its bias.
    * A (point, source) pair whose ``1 - cos`` reaches ``max_dissimilarity`` is an outlier
      (FatesGS's rule) and contributes nothing.

    Args:
        depth_ref: ``(H, W)`` camera-frame z in mm, finite where ``valid``.
        K_ref, world_to_cam_ref: ``(3, 3)`` intrinsics at ``(H, W)``, ``(4, 4)`` world(mm)
            -> camera (numpy or torch).
        feats_ref: ``(C, h, w)`` reference features (any scale, see :func:`sample_features`).
        sources: ``[(K_i, world_to_cam_i, feats_i, (H_i, W_i)), ...]``; the image size may
            be omitted (3-tuples) when it equals ``(H, W)``.
        valid: ``(H, W)`` bool, required: the reference pixels that are surface points
            (for a render, where alpha is high enough; for a depth map, its validity
            mask). Pixels with depth 0 are never points; a non-finite depth inside
            ``valid`` raises ``ValueError``.
        ref_image_size: image size ``feats_ref`` refers to, default ``(H, W)``.
        max_dissimilarity: a (point, source) pair with ``1 - cos`` at or above this is an
            outlier (occluded in the source, specular, mismatched) and contributes nothing
            (FatesGS keeps pairs below 0.5); ``None``: keep every pair.
        return_terms: also return the per-point sum over sources ``(N,)`` and the ``(H, W)``
            point mask (``valid & (depth > 0)`` and a non-zero reference feature).

    Returns the mean over the N reference points (valid, depth > 0, a non-zero feature) of
    ``sum_i w (1 - cos)`` (0 when there is none).
    """
    H, W = depth_ref.shape
    z = depth_ref.reshape(-1)
    mask = torch.as_tensor(valid, device=z.device).bool()
    if mask.shape != depth_ref.shape:
        raise ValueError(f"gcf_loss: valid {tuple(mask.shape)} must have the depth's shape {(H, W)}")
    mask = mask.reshape(-1)
    if not torch.isfinite(z[mask]).all():
        raise ValueError("gcf_loss: non-finite depth inside the validity mask (no depth is 0, outside the mask)")
    idx = torch.nonzero(mask & (z > 0)).squeeze(1)
    ys = torch.div(idx, W, rounding_mode="floor").to(z.dtype)
    xs = (idx % W).to(z.dtype)
    f_ref, inside_ref = sample_features(feats_ref.to(z.dtype), torch.stack([xs, ys], -1), ref_image_size or (H, W))
    informative = inside_ref & _nonzero(f_ref)
    idx, xs, ys, f_ref = idx[informative], xs[informative], ys[informative], f_ref[:, informative]
    points = torch.zeros_like(mask)
    points[idx] = True
    zs = z[idx]
    K = _t(K_ref, z)
    T = _t(world_to_cam_ref, z)
    pix_h = torch.stack([xs, ys, torch.ones_like(xs)], -1)
    rays = torch.linalg.solve(K, pix_h.t()).t()  # camera-frame rays with z = 1
    x_cam = rays * zs.unsqueeze(1)
    R, t = T[:3, :3], T[:3, 3]
    x_world = (x_cam - t) @ R  # R^T (x_cam - t), row vectors
    o_ref = -R.t() @ t
    v_ref = F.normalize(x_world - o_ref, dim=1)

    total = torch.zeros_like(zs)
    for src in sources:
        K_i, T_i, feats_i = _t(src[0], z), _t(src[1], z), src[2].to(z.dtype)
        size_i = tuple(src[3]) if len(src) > 3 else (H, W)
        R_i, t_i = T_i[:3, :3], T_i[:3, 3]
        x_i = x_world @ R_i.t() + t_i
        front = x_i[:, 2] > MIN_Z_MM
        z_i = torch.where(front, x_i[:, 2], torch.ones_like(x_i[:, 2]))  # avoid 0-division behind
        uvw = x_i @ K_i.t()
        p_i = uvw[:, :2] / z_i.unsqueeze(1)
        f_i, inside = sample_features(feats_i, p_i, size_i)
        o_i = -R_i.t() @ t_i
        v_i = F.normalize(x_world - o_i, dim=1)
        w = (v_ref * v_i).sum(1).clamp_min(0.0).detach()
        dissimilarity = 1.0 - cosine(f_ref, f_i)
        keep = front & inside & _nonzero(f_i)
        if max_dissimilarity is not None:
            keep &= dissimilarity.detach() < max_dissimilarity
        total = total + torch.where(keep, w * dissimilarity, torch.zeros_like(dissimilarity))
    loss = total.sum() / max(len(idx), 1)
    if return_terms:
        return loss, total, points.view(H, W)
    return loss
