"""The ``mast3r`` backend: a user-supplied MASt3R ONNX model (contract below and in
docs/init.md) turned into metric depth maps aligned to the *known* cameras.

For every ordered pair (i, j) of input views the model gives view i's pointmap in
camera i's frame (``pts3d_1``, an unknown scale) and view j's pointmap in the same frame
(``pts3d_2``). Pixels of i and j are matched through the two pointmaps (reciprocal
nearest neighbours in 3D among confident pixels), the matches are checked against the
epipolar geometry of the known cameras and triangulated with them, which gives metric
depths (mm) in camera i. A robust fit (RANSAC, then least squares on the inliers) of
``z_metric = s * z_pred`` (or ``s * z_pred + t`` with ``fit_shift``) makes view i's
predicted depth metric. The aligned depths of view i from its pairs are averaged
(weighted by MASt3R's confidence), resized to the scene's resolution, filtered by
confidence, mask and the scene sphere, and fused like the MVS depth maps (geometric
consistency, voxel averaging, normals).

Per-pixel confidence = (1 - 1 / c) * (agreeing other views) / (N - 1), with c >= 1 the
model's confidence.
"""
from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pipeline import geometry
from pipeline.config.init import ConsistencyConfig, InitConfig
from pipeline.data.scene import Scene
from pipeline.init.fusion import check_consistency, fuse_views
from pipeline.init.io import DepthMap, InitResult
from pipeline.init.mvs import sphere_depth_range
from pipeline.init.sfm import epipolar_distance, fundamental, triangulate_tracks
from pipeline.onnx_models import ModelContract, ModelError, OnnxModel, TensorSpec, load_onnx

MAST3R_CONTRACT = ModelContract(
    name="mast3r",
    inputs=(
        TensorSpec("img1", 4, "float32", (1, 3, "H", "W"), "RGB scaled to [-1, 1]; H, W multiples of 16"),
        TensorSpec("img2", 4, "float32", (1, 3, "H", "W"), "RGB scaled to [-1, 1], same size as img1"),
    ),
    outputs=(
        TensorSpec("pts3d_1", 4, "float32", (1, "H", "W", 3), "view-1 pixels' 3D points in camera 1's frame"),
        TensorSpec("conf_1", 3, "float32", (1, "H", "W"), "confidence of pts3d_1 (>= 1)"),
        TensorSpec("pts3d_2", 4, "float32", (1, "H", "W", 3), "view-2 pixels' 3D points in camera 1's frame"),
        TensorSpec("conf_2", 3, "float32", (1, "H", "W"), "confidence of pts3d_2 (>= 1)"),
    ),
    doc="MASt3R (Leroy et al., ECCV 2024) pair head: pointmaps of both views in view 1's camera frame",
)


def model_size(model: OnnxModel, width: int, height: int, long_side: int) -> tuple[int, int]:
    """Network input ``(w, h)``: the model's fixed size when it has one, else the image
    resized to ``long_side`` on its long side with both sides rounded to multiples of 16."""
    shape = model.session.get_inputs()[0].shape
    if isinstance(shape[2], int) and isinstance(shape[3], int) and shape[2] > 0 and shape[3] > 0:
        return int(shape[3]), int(shape[2])
    s = long_side / max(width, height)
    return max(16, int(round(width * s / 16)) * 16), max(16, int(round(height * s / 16)) * 16)


def preprocess(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``(H, W, 3)`` RGB in [0, 1] -> ``(1, 3, h, w)`` float32 in [-1, 1] at ``size = (w, h)``."""
    small = cv2.resize(image.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray((small * 2.0 - 1.0).transpose(2, 0, 1)[None], dtype=np.float32)


def to_full_res(px_small: np.ndarray, small: tuple[int, int], full: tuple[int, int]) -> np.ndarray:
    """Pixel coordinates (x, y) at ``small = (w, h)`` -> at ``full`` (integer centres)."""
    sx, sy = full[0] / small[0], full[1] / small[1]
    return np.c_[(px_small[:, 0] + 0.5) * sx - 0.5, (px_small[:, 1] + 0.5) * sy - 0.5]


def reciprocal_matches(p1: np.ndarray, ok1: np.ndarray, p2: np.ndarray, ok2: np.ndarray,
                       stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Reciprocal nearest neighbours in 3D between two ``(h, w, 3)`` pointmaps (same frame).

    Queries are the ``ok1`` pixels of view 1 on a ``stride`` grid, searched among all
    ``ok2`` pixels of view 2; a match is kept when view 2's point has that very query
    as its nearest neighbour among all ``ok1`` pixels. Returns flat pixel indices.
    """
    h, w = ok1.shape
    grid = np.zeros((h, w), bool)
    grid[::stride, ::stride] = True
    all1, all2 = np.flatnonzero(ok1), np.flatnonzero(ok2)
    q1 = np.flatnonzero(ok1 & grid)
    if len(q1) == 0 or len(all2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    pts1, pts2 = p1.reshape(-1, 3), p2.reshape(-1, 3)
    _, nn12 = cKDTree(pts2[all2]).query(pts1[q1])
    m2 = all2[nn12]
    _, nn21 = cKDTree(pts1[all1]).query(pts2[m2])
    mutual = all1[nn21] == q1
    return q1[mutual], m2[mutual]


def robust_fit(z_pred: np.ndarray, z_metric: np.ndarray, fit_shift: bool, iters: int, inlier_rel: float,
               rng: np.random.Generator) -> tuple[float, float, np.ndarray]:
    """RANSAC fit of ``z_metric ~ s * z_pred (+ t)``, refined by least squares on the
    inliers (relative error < ``inlier_rel``). Returns ``(s, t, inliers)``."""
    n = len(z_pred)
    k = 2 if fit_shift else 1
    if n < k + 1:
        raise ValueError(f"too few matches ({n}) to fit a depth scale")
    best = np.zeros(n, bool)
    for _ in range(iters):
        idx = rng.choice(n, k, replace=False)
        if fit_shift:
            dz = z_pred[idx[1]] - z_pred[idx[0]]
            if abs(dz) < 1e-12:
                continue
            s = (z_metric[idx[1]] - z_metric[idx[0]]) / dz
            t = z_metric[idx[0]] - s * z_pred[idx[0]]
        else:
            s, t = z_metric[idx[0]] / z_pred[idx[0]], 0.0
        if s <= 0:
            continue
        inl = np.abs(s * z_pred + t - z_metric) < inlier_rel * z_metric
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < k + 1:
        raise ValueError("no consistent depth scale among the matches")
    for _ in range(3):  # least squares on the inliers, re-selecting the inliers
        zp, zm = z_pred[best], z_metric[best]
        if fit_shift:
            s, t = np.linalg.lstsq(np.c_[zp, np.ones_like(zp)], zm, rcond=None)[0]
        else:
            s, t = float(zp @ zm / (zp @ zp)), 0.0
        new = np.abs(s * z_pred + t - z_metric) < inlier_rel * z_metric
        if new.sum() < k + 1 or np.array_equal(new, best):
            break
        best = new
    return float(s), float(t), best


def align_pair(scene: Scene, i: int, j: int, out: dict[str, np.ndarray], small: tuple[int, int],
               cfg: InitConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, dict]:
    """Metric depth (mm, camera i, at ``small``) and confidence of view i from the model's
    output on the pair (i, j); plus facts about the fit."""
    p = cfg.mast3r
    P1, C1 = out["pts3d_1"][0].astype(np.float64), out["conf_1"][0]
    P2, C2 = out["pts3d_2"][0].astype(np.float64), out["conf_2"][0]
    ok1 = (C1 >= p.min_conf) & (P1[..., 2] > 0)
    ok2 = C2 >= p.min_conf
    m1, m2 = reciprocal_matches(P1, ok1, P2, ok2, p.match_subsample)
    w_s, h_s = small
    full = (scene.width, scene.height)
    x1 = to_full_res(np.c_[m1 % w_s, m1 // w_s].astype(np.float64), small, full)
    x2 = to_full_res(np.c_[m2 % w_s, m2 // w_s].astype(np.float64), small, full)
    F = fundamental(scene.K[i], scene.world_to_cam[i], scene.K[j], scene.world_to_cam[j])
    good = epipolar_distance(F, x1, x2) < p.epipolar_px
    m1, x1, x2 = m1[good], x1[good], x2[good]
    Pw = scene.projections_world()[[i, j], :3, :]
    X = triangulate_tracks(Pw, np.stack([x1, x2], 1), np.ones((len(x1), 2), bool))
    z_metric = np.zeros(len(X))
    ok = np.ones(len(X), bool)
    for v, x in ((i, x1), (j, x2)):
        px, z = geometry.project(scene.K[v], scene.world_to_cam[v], X)
        ok &= (z > 0) & (np.linalg.norm(px - x, axis=1) < p.epipolar_px)
        if v == i:
            z_metric = z
    z_pred = P1.reshape(-1, 3)[m1, 2]
    ok &= z_pred > 0
    s, t, inl = robust_fit(z_pred[ok], z_metric[ok], p.fit_shift, p.ransac_iters, p.inlier_rel, rng)
    depth = s * P1[..., 2] + t
    conf = np.where(ok1 & (depth > 0), C1, 0.0)
    facts = {"pair": [scene.view_ids[i], scene.view_ids[j]], "matches": int(ok.sum()), "inliers": int(inl.sum()),
             "scale": s, "shift_mm": t}
    return depth, conf, facts


def run(scene: Scene, cfg: InitConfig, model: OnnxModel | None = None) -> InitResult:
    p = cfg.mast3r
    if model is None:
        if not p.model:
            raise ModelError("the mast3r backend needs a MASt3R ONNX model: pass --model PATH or set init.mast3r.model "
                             "(docs/init.md describes the expected inputs and outputs)")
        model = load_onnx(p.model, MAST3R_CONTRACT)
    rng = np.random.default_rng(cfg.seed)
    N, H, W = scene.num_views, scene.height, scene.width
    small = model_size(model, W, H, p.long_side)
    inputs = [preprocess(img, small) for img in scene.images]
    depths = np.zeros((N, H, W), np.float32)
    confs = np.zeros((N, H, W), np.float32)
    fits = []
    for i in range(N):
        num = np.zeros(small[::-1])
        den = np.zeros(small[::-1])
        for j in range(N):
            if j == i:
                continue
            out = model.run(img1=inputs[i], img2=inputs[j])
            try:
                d, c, facts = align_pair(scene, i, j, out, small, cfg, rng)
            except ValueError as exc:
                raise ModelError(f"{model.path}: cannot align the prediction for views "
                                 f"{scene.view_ids[i]}, {scene.view_ids[j]} to the known cameras: {exc}") from exc
            fits.append(facts)
            num += c * d
            den += c
        d_small = np.where(den > 0, num / np.maximum(den, 1e-12), 0.0).astype(np.float32)
        c_small = (den / (N - 1)).astype(np.float32)
        depths[i] = cv2.resize(d_small, (W, H), interpolation=cv2.INTER_LINEAR)
        confs[i] = cv2.resize(c_small, (W, H), interpolation=cv2.INTER_NEAREST)
    # Validity: confident, object mask, inside the scene sphere; bilinear resizing mixes
    # depths across edges, so pixels next to an unconfident one are dropped too.
    valid = confs >= p.min_conf
    valid &= cv2.erode(valid.astype(np.uint8).transpose(1, 2, 0), np.ones((3, 3), np.uint8)).reshape(H, W, -1).transpose(2, 0, 1) > 0
    if scene.masks is not None:
        valid &= scene.masks
    ys, xs = np.mgrid[0:H, 0:W]
    pix = np.c_[xs.ravel(), ys.ravel()].astype(np.float64)
    for i in range(N):
        near, far = sphere_depth_range(scene.K[i], scene.world_to_cam[i], scene.norm_to_world, pix, cfg.mvs.sphere_margin)
        d = depths[i].ravel()
        valid[i] &= ((d >= np.nan_to_num(near, nan=np.inf)) & (d <= np.nan_to_num(far, nan=-np.inf))).reshape(H, W)
    cons = ConsistencyConfig(px=p.consistency_px, rel_depth=p.consistency_rel_depth, min_views=cfg.consistency.min_views)
    views = check_consistency(depths, valid, scene.K, scene.world_to_cam, scene.images, cons)
    maps, point_conf = [], []
    for i, vp in enumerate(views):
        c = (1.0 - 1.0 / np.maximum(confs[i], 1.0)) * vp.count / max(N - 1, 1)
        maps.append(DepthMap(scene.view_ids[i], np.where(vp.valid, depths[i], 0.0).astype(np.float32),
                             np.where(vp.valid, c, 0.0).astype(np.float32), vp.valid,
                             scene.K[i], scene.world_to_cam[i]))
        point_conf.append(c[vp.pixels[:, 0], vp.pixels[:, 1]])
    cloud = fuse_views(views, point_conf, scene.world_to_cam, cfg.voxel_norm * scene.norm_scale_mm, cfg.normal_knn)
    info = {"model": str(model.path), "providers": model.providers, "model_size": list(small), "fits": fits,
            "consistent_fraction": [float(v.valid.sum() / max(1, m.sum())) for v, m in zip(views, valid)]}
    return InitResult(cloud, maps, info)
