"""Held-out-view scores where no ground-truth geometry exists: the trained surfels rendered
at every view not used for training, their alpha against the view's mask (IoU, alpha >
0.5) and their colour against the image (PSNR over the mask's pixels), and the extracted
mesh's silhouette against the same masks (the mesh is what the pipeline delivers; the
surfels' alpha can differ from it, e.g. where thin or grazing surfels are not fused). The
same IoU of the visual hull of the input masks is the trivial reference a reconstruction
must beat.
"""
from __future__ import annotations

import numpy as np
import torch

from pipeline.data.scene import Scene
from pipeline.rasterizer import Camera, rasterize
from pipeline.raycast import MeshCaster
from pipeline.surfels import SurfelParams

ALPHA_SILHOUETTE = 0.5


def iou(pred: np.ndarray, gt: np.ndarray) -> float:
    union = np.logical_or(pred, gt).sum()
    return float(np.logical_and(pred, gt).sum() / union) if union else 1.0


def masked_psnr(render: np.ndarray, image: np.ndarray, mask: np.ndarray) -> float | None:
    """PSNR (dB, peak 1) of ``render`` vs ``image`` over the pixels of ``mask``."""
    if not mask.any():
        return None
    mse = float(np.mean((render[mask] - image[mask]) ** 2))
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def rays_in_unit_sphere(K: np.ndarray, world_to_cam_norm: np.ndarray, width: int, height: int, samples: int) -> np.ndarray:
    """``(H, W, samples, 3)`` points (normalised frame) evenly along each pixel's ray inside
    the unit sphere; NaN for rays that miss it."""
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    d_cam = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T
    R, t = world_to_cam_norm[:3, :3], world_to_cam_norm[:3, 3]
    o = -R.T @ t
    d = d_cam @ R  # R^T d, as rows
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    b = d @ o
    disc = b * b - (o @ o - 1.0)
    hit = disc > 0
    root = np.sqrt(np.where(hit, disc, 0.0))
    t0, t1 = -b - root, -b + root
    s = (np.arange(samples) + 0.5) / samples
    tt = t0[..., None] + (t1 - t0)[..., None] * s
    pts = o + tt[..., None] * d[:, :, None, :]
    pts[~hit] = np.nan
    return pts


def visual_hull_silhouettes(inputs: Scene, targets: Scene, samples: int = 160) -> np.ndarray:
    """``(M, H, W)`` silhouettes, in the target views, of the visual hull of the input masks:
    a pixel is in when some point of its ray inside the unit sphere projects inside every
    input mask (a point outside an input image is outside the hull)."""
    if inputs.masks is None:
        raise ValueError(f"{inputs.source}: the visual hull needs input masks")
    w2c_in = inputs.world_to_cam_normalised()
    w2c_t = targets.world_to_cam_normalised()
    out = np.zeros((targets.num_views, targets.height, targets.width), bool)
    for m in range(targets.num_views):
        pts = rays_in_unit_sphere(targets.K[m], w2c_t[m], targets.width, targets.height, samples).reshape(-1, 3)
        inside = np.isfinite(pts[:, 0])
        for K, T, mask in zip(inputs.K, w2c_in, inputs.masks):
            cam = pts @ T[:3, :3].T + T[:3, 3]
            z = cam[:, 2]
            with np.errstate(invalid="ignore", divide="ignore"):
                uv = (cam @ K.T)[:, :2] / z[:, None]
                col, row = np.round(uv[:, 0]), np.round(uv[:, 1])
                ok = (z > 0) & (col >= 0) & (col < inputs.width) & (row >= 0) & (row < inputs.height)
            hit = np.zeros(len(pts), bool)
            hit[ok] = mask[row[ok].astype(np.int64), col[ok].astype(np.int64)]
            inside &= hit
        out[m] = inside.reshape(targets.height, targets.width, samples).any(axis=2)
    return out


@torch.no_grad()
def heldout_scores(params: SurfelParams, inputs: Scene, heldout: Scene, background: float = 0.0,
                   backend: str = "cpu", hull_samples: int = 160, mesh: MeshCaster | None = None) -> dict:
    """Mask IoU and masked PSNR of the surfels at every held-out view, the visual hull's IoU
    and, given the mesh (world frame, mm), the IoU of its silhouette (a pixel whose centre
    ray hits the mesh)."""
    surf = params.surfels(params.sh_degree_max)
    hull = visual_hull_silhouettes(inputs, heldout, hull_samples)
    w2c = heldout.world_to_cam_normalised()
    per_view = {}
    for m, v in enumerate(heldout.view_ids):
        out = rasterize(surf, Camera(heldout.K[m], w2c[m], heldout.width, heldout.height), backend)
        alpha = out.alpha.double().numpy()
        rgb = np.clip(out.features.double().numpy() + background * (1 - alpha[..., None]), 0, 1)
        gt = heldout.masks[m]
        per_view[str(v)] = {"iou": iou(alpha > ALPHA_SILHOUETTE, gt), "hull_iou": iou(hull[m], gt),
                            "psnr_masked_db": masked_psnr(rgb, heldout.images[m].astype(np.float64), gt)}
        if mesh is not None:
            hit = mesh.cast(heldout.K[m], heldout.world_to_cam[m], heldout.height, heldout.width).depth_mm > 0
            per_view[str(v)]["mesh_iou"] = iou(hit, gt)
    vals = list(per_view.values())
    psnrs = [x["psnr_masked_db"] for x in vals if x["psnr_masked_db"] is not None]
    return {
        "views": len(vals), "size": [heldout.width, heldout.height],
        "iou_mean": float(np.mean([x["iou"] for x in vals])),
        "hull_iou_mean": float(np.mean([x["hull_iou"] for x in vals])),
        "psnr_masked_db_mean": float(np.mean(psnrs)) if psnrs else None,
        "mesh_iou_mean": float(np.mean([x["mesh_iou"] for x in vals])) if mesh is not None else None,
        "per_view": per_view,
    }
