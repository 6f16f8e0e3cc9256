"""Error of the depth a model renders at the input views against the ground truth's depth
there (synthetic scenes), per pixel: the quantity the TSDF mesh is fused from, so a mesh's
accuracy cannot beat it. Its signed median says whether the surface sits in front of the
truth (negative: towards the camera) or behind it; its median absolute value and the share
above 1 mm say how noisy it is. Depths are camera-frame z in world mm, 0 where a map has
none; pixel centres at integer coordinates (the GT is ray-cast through the same centres).
"""
from __future__ import annotations

import math

import numpy as np

MAX_ERR_MM = 5.0  # beyond this a pixel is a different surface (an edge, a floater), not depth noise


def depth_errors(depths_mm: np.ndarray, gt_depths_mm: np.ndarray, masks: np.ndarray | None = None) -> dict:
    """Per-pixel errors ``depth - gt`` over the pixels (inside ``masks``) where both have depth,
    all views ``(N, H, W)`` pooled. Returns ``coverage`` (share of the masked pixels, or of
    the GT's pixels without masks, that have a depth), ``median_abs_mm``, ``share_above_1mm``
    and ``outliers`` (share with ``|err| > MAX_ERR_MM``) over all compared pixels, and
    ``signed_median_mm`` / ``mean_abs_mm`` over those within ``MAX_ERR_MM``. NaN figures
    where no pixel compares."""
    d, g = np.asarray(depths_mm, np.float64), np.asarray(gt_depths_mm, np.float64)
    if d.shape != g.shape or d.ndim != 3:
        raise ValueError(f"depths and GT depths must both be (N, H, W), got {d.shape} and {g.shape}")
    region = (g > 0) if masks is None else np.asarray(masks, bool)
    if region.shape != d.shape:
        raise ValueError(f"masks must be {d.shape}, got {region.shape}")
    both = region & (d > 0) & (g > 0)
    err = (d - g)[both]
    coverage = float((region & (d > 0)).sum() / max(region.sum(), 1))
    if not len(err):
        return {"coverage": coverage, **dict.fromkeys(
            ("median_abs_mm", "share_above_1mm", "outliers", "outliers_in_front", "outlier_error_share",
             "signed_median_mm", "mean_abs_mm"), math.nan)}
    near = err[np.abs(err) <= MAX_ERR_MM]
    total = float(np.abs(err).sum())
    return {
        "coverage": coverage,
        "median_abs_mm": float(np.median(np.abs(err))),
        "share_above_1mm": float(np.mean(np.abs(err) > 1.0)),
        "outliers": float(np.mean(np.abs(err) > MAX_ERR_MM)),
        "outliers_in_front": float(np.mean(err < -MAX_ERR_MM)),
        "outlier_error_share": float(np.abs(err[np.abs(err) > MAX_ERR_MM]).sum() / total) if total > 0 else 0.0,
        "signed_median_mm": float(np.median(near)) if len(near) else math.nan,
        "mean_abs_mm": float(np.mean(np.abs(near))) if len(near) else math.nan,
    }


def gt_depths_mm(gt_vertices_mm: np.ndarray, gt_triangles: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
                 width: int, height: int) -> np.ndarray:
    """``(N, H, W)`` GT depth (camera z, mm; 0 = miss) ray-cast through each camera's pixel centres."""
    from pipeline.raycast import MeshCaster

    caster = MeshCaster(gt_vertices_mm, gt_triangles)
    return np.stack([caster.cast(K[i], world_to_cam[i], height, width).depth_mm for i in range(len(K))])
