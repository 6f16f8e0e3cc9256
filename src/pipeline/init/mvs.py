"""Plane-sweep multi-view stereo with known cameras (the default init backend).

For each reference view, fronto-parallel planes (uniform in inverse depth, so roughly
one pixel of disparity apart) sweep the depth range where the reference rays cross the
scene's unit sphere. Each source view is warped onto every plane (bilinear, a numba kernel) and
compared with the reference by zero-mean normalised cross-correlation over a square
window (box filters), which is invariant to gain and offset changes of the lighting.
The per-pixel score is the mean NCC over the source views that see the point, or the best
source's NCC less a margin where that is higher (a surface strip beside an occluding edge
is hidden from some sources, and the mean alone rejects it);
winner-take-all picks a plane, and a parabola through the scores of the neighbouring
planes (in inverse depth) refines it below the plane spacing. Masks are honoured: only
object pixels of the reference get a depth, and hypotheses that land outside a source
view's mask score as no match.

All depths are camera-frame z in mm; all positions world-frame mm.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from scipy import ndimage

from pipeline import geometry
from pipeline.config.init import InitConfig, MVSConfig
from pipeline.data.scene import Scene
from pipeline.init.fusion import ViewPoints, check_consistency, fuse_views
from pipeline.init.hole_fill import enclosed_holes, flat_rimmed, harmonic_fill, contradicted
from pipeline.init.io import DepthMap, InitResult


def to_grey(images: np.ndarray) -> np.ndarray:
    """``(..., 3)`` RGB in [0, 1] -> luminance (Rec. 601)."""
    return images @ np.array([0.299, 0.587, 0.114], dtype=images.dtype)


def normalised_grey(images: np.ndarray, masks: np.ndarray | None) -> np.ndarray:
    """``(N, H, W, 3)`` RGB -> ``(N, H, W)`` float32 luminance divided by each view's mean
    luminance inside its object mask (over all pixels without masks).

    NCC ignores gain, but the contrast threshold (``min_rel_std``) and NCC's variance
    floor do not: on a dark capture (object mean ~0.06) an absolute threshold rejects most
    windows. After this, contrast is relative to the view's own exposure.
    """
    grey = to_grey(np.asarray(images, np.float32))
    out = np.empty(grey.shape, np.float32)
    for i, g in enumerate(grey):
        inside = g[masks[i]] if masks is not None and masks[i].any() else g
        mean = float(inside.mean())
        out[i] = g / mean if mean > 0 else g
    return out


def sphere_depth_range(K: np.ndarray, world_to_cam: np.ndarray, norm_to_world: np.ndarray,
                       pixels: np.ndarray, margin: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel ``(near, far)`` camera z (mm) where each ray crosses the scene sphere.

    The sphere is the normalised unit sphere scaled by ``margin`` (world centre
    ``norm_to_world[:3, 3]``, radius ``margin * norm_to_world[0, 0]`` mm). Rays that miss
    it get ``near = far = nan``. ``pixels`` is ``(M, 2)`` (x, y).
    """
    centre = norm_to_world[:3, 3]
    radius = margin * norm_to_world[0, 0]
    c_cam = world_to_cam[:3, :3] @ centre + world_to_cam[:3, 3]
    rays = geometry.pixel_rays(K, pixels[:, 0], pixels[:, 1])
    # |t r - c|^2 = R^2 with t the camera z (rays have unit z).
    a = np.einsum("ij,ij->i", rays, rays)
    b = rays @ c_cam
    disc = b * b - a * (c_cam @ c_cam - radius * radius)
    with np.errstate(invalid="ignore"):
        s = np.sqrt(disc)
    near = np.where(disc > 0, (b - s) / a, np.nan)
    far = np.where(disc > 0, (b + s) / a, np.nan)
    return np.maximum(near, 1e-3 * radius), far


def box_mean(x: np.ndarray, k: int) -> np.ndarray:
    """Mean over a ``k x k`` window of a 2-D float32 array (OpenCV's box filter, which
    keeps float64 running sums: NCC subtracts nearly equal window moments)."""
    return cv2.boxFilter(x, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT_101)


@numba.njit(parallel=True, cache=True)
def _warp_moments(A, b, Z, img, smask, R, M, x0, y0, mom, in_mask, seen) -> None:
    """Warp a source onto the reference at per-pixel depths ``Z`` (mm): a plane of the
    sweep, or the smoothed surface of the refinement.

    Reference pixel ``(x0 + x, y0 + y)`` maps to source pixel ``q = A [x, y, 1] z + b``
    (homogeneous). Writes ``mom[y, x] = M * (S, S*S, R*S)`` with ``S`` the bilinear source
    sample (coordinates clamped to the image, so windows at the border stay defined) and
    ``M`` the reference object mask (window moments count object pixels only),
    ``seen`` (in front and inside the image) and ``in_mask`` (source mask, nearest).
    """
    h, w = R.shape
    H, W = img.shape
    for y in numba.prange(h):
        py = y0 + y
        for x in range(w):
            px = x0 + x
            z = Z[y, x]
            q0 = (A[0, 0] * px + A[0, 1] * py + A[0, 2]) * z + b[0]
            q1 = (A[1, 0] * px + A[1, 1] * py + A[1, 2]) * z + b[1]
            q2 = (A[2, 0] * px + A[2, 1] * py + A[2, 2]) * z + b[2]
            s = 0.0
            ok = False
            if q2 > 0:
                u = q0 / q2
                v = q1 / q2
                ok = (u >= 0) and (u <= W - 1) and (v >= 0) and (v <= H - 1)
                uc = min(max(u, 0.0), W - 1.0)
                vc = min(max(v, 0.0), H - 1.0)
                i0 = min(int(vc), H - 2)
                j0 = min(int(uc), W - 2)
                fy = vc - i0
                fx = uc - j0
                s = ((1 - fy) * ((1 - fx) * img[i0, j0] + fx * img[i0, j0 + 1])
                     + fy * ((1 - fx) * img[i0 + 1, j0] + fx * img[i0 + 1, j0 + 1]))
                in_mask[y, x] = smask[int(vc + 0.5), int(uc + 0.5)]
            seen[y, x] = ok
            s *= M[y, x]
            mom[y, x, 0] = s
            mom[y, x, 1] = s * s
            mom[y, x, 2] = R[y, x] * s


@numba.njit(parallel=True, cache=True)
def _accumulate_ncc(moments, frac, mu_r, var_r, in_mask, seen, acc, cnt, best) -> None:
    """NCC from masked window moments (box means of ``M S, M S^2, M R S`` divided by the
    window's object fraction ``frac``), added to ``acc``/``cnt`` and maxed into ``best``
    where the source sees the point; -1 where it sees it outside its object mask."""
    h, w = mu_r.shape
    for y in numba.prange(h):
        for x in range(w):
            if not seen[y, x]:
                continue
            if in_mask[y, x] and frac[y, x] > 0:
                mu_s = moments[y, x, 0] / frac[y, x]
                var_s = max(moments[y, x, 1] / frac[y, x] - mu_s * mu_s, 0.0)
                ncc = (moments[y, x, 2] / frac[y, x] - mu_r[y, x] * mu_s) / np.sqrt(var_r[y, x] * var_s + 1e-8)
            else:
                ncc = -1.0
            acc[y, x] += ncc
            cnt[y, x] += 1.0
            best[y, x] = max(best[y, x], ncc)


@dataclass
class SweepResult:
    depth_mm: np.ndarray  # (H, W) float32, 0 where invalid
    score: np.ndarray  # (H, W) float32 score of the winner (mean or margin-reduced best NCC), -1 where invalid
    valid: np.ndarray  # (H, W) bool
    num_depths: int


def _relative_warp(K_r, T_r, K_s, T_s):
    """``(A, b)`` with source pixel ~ ``A @ [x, y, 1] * z + b`` for reference depth z."""
    T_rs = T_s @ geometry.rigid_inverse(T_r)
    A = K_s @ T_rs[:3, :3] @ np.linalg.inv(K_r)
    b = K_s @ T_rs[:3, 3]
    return A, b


def _plane_count(warps, pix: np.ndarray, z_near: float, z_far: float, step_px: float, max_depths: int) -> int:
    """Planes ``step_px`` pixels of disparity apart between ``z_near`` and ``z_far`` in the
    widest-baseline source (95th percentile over a sample of the ``(M, 2)`` pixels)."""
    sel = pix[:: max(1, len(pix) // 2000)]
    ph = np.c_[sel, np.ones(len(sel))]
    span = 0.0
    for A, b in warps:
        q_near = (ph @ A.T) * z_near + b
        q_far = (ph @ A.T) * z_far + b
        d = np.linalg.norm(q_near[:, :2] / q_near[:, 2:] - q_far[:, :2] / q_far[:, 2:], axis=1)
        span = max(span, float(np.percentile(d, 95)))
    return int(min(max_depths, max(3, math.ceil(span / step_px) + 1)))


def _peak(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Winner-take-all over axis 0 and the vertex of the parabola through the winner's
    and its neighbours' scores. Returns ``(index, score, offset in steps, interior)``;
    winners at either end or without a maximum are not ``interior``."""
    n = len(cost)
    best = cost.argmax(0)
    best_score = np.take_along_axis(cost, best[None], 0)[0]
    idx = np.clip(best, 1, n - 2)
    c_m = np.take_along_axis(cost, (idx - 1)[None], 0)[0]
    c_0 = np.take_along_axis(cost, idx[None], 0)[0]
    c_p = np.take_along_axis(cost, (idx + 1)[None], 0)[0]
    curv = c_m - 2 * c_0 + c_p
    interior = (best > 0) & (best < n - 1) & (curv < 0)
    offset = np.clip(np.where(interior, 0.5 * (c_m - c_p) / np.where(interior, curv, 1.0), 0.0), -0.5, 0.5)
    return best, best_score, offset, interior


def _smooth_inverse_depth(inv_depth: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """5x5 median of the inverse depth, with pixels not ``ok`` first filled from the
    nearest ``ok`` pixel (so outliers and holes do not bend the surface)."""
    idx = ndimage.distance_transform_edt(~ok, return_distances=False, return_indices=True)
    filled = inv_depth[idx[0], idx[1]].astype(np.float32)
    return cv2.medianBlur(filled, 5).astype(np.float64)


def sweep_view(scene: Scene, ref: int, params: MVSConfig, grey: np.ndarray | None = None) -> SweepResult:
    """Depth map of view ``ref`` by plane sweep against every other view of ``scene``.

    ``grey``: the views' :func:`normalised_grey` (computed when not given).
    """
    H, W = scene.height, scene.width
    grey = normalised_grey(scene.images, scene.masks) if grey is None else grey
    mask = scene.masks[ref] if scene.masks is not None else np.ones((H, W), bool)
    srcs = [i for i in range(scene.num_views) if i != ref]
    out = SweepResult(np.zeros((H, W), np.float32), np.full((H, W), -1.0, np.float32), np.zeros((H, W), bool), 0)
    if not srcs or not mask.any():
        return out

    # Work on the mask's bounding box (plus half a window) only.
    k = params.window
    ys, xs = np.nonzero(mask)
    y0, y1 = max(ys.min() - k, 0), min(ys.max() + k + 1, H)
    x0, x1 = max(xs.min() - k, 0), min(xs.max() + k + 1, W)
    h, w = y1 - y0, x1 - x0
    gy, gx = np.mgrid[y0:y1, x0:x1]
    pix = np.stack([gx.ravel(), gy.ravel()], 1).astype(np.float64)
    near, far = sphere_depth_range(scene.K[ref], scene.world_to_cam[ref], scene.norm_to_world, pix, params.sphere_margin)
    in_box_mask = mask[y0:y1, x0:x1].ravel() & np.isfinite(near)
    if not in_box_mask.any():
        return out
    z_near, z_far = float(near[in_box_mask].min()), float(far[in_box_mask].max())

    # Plane count: disparity span between z_near and z_far in the widest-baseline source.
    warps = [_relative_warp(scene.K[ref], scene.world_to_cam[ref], scene.K[s], scene.world_to_cam[s]) for s in srcs]
    D = _plane_count(warps, pix[in_box_mask], z_near, z_far, params.depth_step_px, params.max_depths)
    inv_planes = np.linspace(1.0 / z_far, 1.0 / z_near, D)  # index 0 = far

    ref_img = np.ascontiguousarray(grey[ref, y0:y1, x0:x1], dtype=np.float32)
    # Windows count object pixels only: background next to a silhouette is at another
    # depth, and its contrast with the object would otherwise be matched as texture.
    M = np.ascontiguousarray(mask[y0:y1, x0:x1], dtype=np.float32)
    frac = box_mean(M, k)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu_r = np.where(frac > 0, box_mean(M * ref_img, k) / frac, 0.0).astype(np.float32)
        var_r = np.where(frac > 0, np.maximum(box_mean(M * ref_img * ref_img, k) / frac - mu_r * mu_r, 0.0),
                         0.0).astype(np.float32)
    near_b = np.nan_to_num(near, nan=np.inf).reshape(h, w)
    far_b = np.nan_to_num(far, nan=-np.inf).reshape(h, w)
    src_data = []
    for s, (A, b) in zip(srcs, warps):
        smask = scene.masks[s] if scene.masks is not None else np.ones((H, W), bool)
        src_data.append((A, b, np.ascontiguousarray(grey[s], dtype=np.float32), np.ascontiguousarray(smask, bool)))

    mom = np.empty((h, w, 3), np.float32)
    in_mask = np.zeros((h, w), bool)
    seen = np.zeros((h, w), bool)

    def score(Z: np.ndarray) -> np.ndarray:
        """Score of per-pixel depths ``Z``: ``max(mean NCC over the sources, best source's
        NCC - params.best_source_margin)``; -1 where no source sees the point or ``Z`` is
        outside the pixel's sphere interval (not the object)."""
        acc = np.zeros((h, w), np.float32)
        cnt = np.zeros((h, w), np.float32)
        best = np.full((h, w), -1.0, np.float32)
        for A, b, img, smask in src_data:
            _warp_moments(A, b, Z, img, smask, ref_img, M, x0, y0, mom, in_mask, seen)
            moments = cv2.boxFilter(mom, -1, (k, k), borderType=cv2.BORDER_REFLECT_101)
            _accumulate_ncc(moments, frac, mu_r, var_r, in_mask, seen, acc, cnt, best)
        agg = np.maximum(acc / np.maximum(cnt, 1.0), best - params.best_source_margin)
        return np.where((cnt > 0) & (Z >= near_b) & (Z <= far_b), agg, -1.0)

    step = (inv_planes[-1] - inv_planes[0]) / (D - 1)
    cost = np.empty((D, h, w), dtype=np.float32)
    Z = np.empty((h, w), np.float64)
    for d in range(D):
        Z.fill(1.0 / inv_planes[d])
        cost[d] = score(Z)
    best, best_score, offset, interior = _peak(cost)
    inv_depth = inv_planes[best] + offset * step
    obj = mask[y0:y1, x0:x1]
    ok = obj & interior & (best_score >= params.min_ncc)

    # Refinement: windows that follow the smoothed surface of the sweep (offset by the
    # same inverse depth everywhere), which removes most of the fronto-parallel bias on
    # slanted surfaces; again winner-take-all and a parabola, now on a finer grid.
    deltas = np.arange(-params.refine_range, params.refine_range + 1e-9, params.refine_step)
    for _ in range(params.refine_iters):
        if not ok.any():
            break
        surface = _smooth_inverse_depth(inv_depth, ok)
        cost = np.stack([score(1.0 / (surface + dl * step)) for dl in deltas])
        best, best_score, offset, interior = _peak(cost)
        inv_depth = surface + (deltas[best] + offset * params.refine_step) * step
        ok = obj & interior & (best_score >= params.min_ncc)
    depth = (1.0 / inv_depth).astype(np.float32)

    valid = ok & (np.sqrt(var_r) >= params.min_rel_std)
    out.depth_mm[y0:y1, x0:x1] = np.where(valid, depth, 0.0)
    out.score[y0:y1, x0:x1] = np.where(valid, best_score, -1.0)
    out.valid[y0:y1, x0:x1] = valid
    out.num_depths = D
    return out


def common_grey(images: np.ndarray, masks: np.ndarray | None) -> np.ndarray:
    """``(N, H, W, 3)`` RGB -> ``(N, H, W)`` float32 luminance divided by one mean over every
    view's object mask: free of the capture's exposure, while the views keep their relative
    brightness (:func:`normalised_grey` divides each view by its own mean, which differs
    with the part of the object it sees and would bias absolute differences)."""
    grey = to_grey(np.asarray(images, np.float32))
    inside = grey[masks] if masks is not None and masks.any() else grey
    mean = float(inside.mean())
    return grey / mean if mean > 0 else grey


def sweep_plain(scene: Scene, ref: int, params: MVSConfig, grey: np.ndarray, todo: np.ndarray) -> SweepResult:
    """Depth of view ``ref`` where NCC cannot match (``todo``, ``(H, W)`` bool), by a coarse
    plane sweep on absolute grey differences.

    NCC ignores gain and offset, so a window of smooth shading (a plain Lambertian surface
    lit from one side: a ramp of grey) matches a shifted copy of itself as well as the true
    one; the squared difference of the views' grey (``grey``: :func:`common_grey`) does not.
    The sweep runs at ``params.fill_width`` pixels wide, where a window spans enough of the
    shading gradient, with fronto-parallel planes one coarse pixel of disparity apart and a
    parabola through the winner; the winner's RMS difference must be at most
    ``params.fill_max_rms`` and the reference window's grey std at least
    ``params.fill_min_std``. Its inverse depth is resized back and kept on ``todo`` pixels
    whose whole neighbourhood was valid. ``score`` is ``1 - rms / fill_max_rms`` (1: exact
    match).
    """
    H, W = scene.height, scene.width
    out = SweepResult(np.zeros((H, W), np.float32), np.full((H, W), -1.0, np.float32), np.zeros((H, W), bool), 0)
    mask = scene.masks[ref] if scene.masks is not None else np.ones((H, W), bool)
    srcs = [i for i in range(scene.num_views) if i != ref]
    if not srcs or not todo.any():
        return out
    w = min(params.fill_width, W)
    h = max(int(round(H * w / W)), 2)
    sx, sy = w / W, h / H

    def down(img: np.ndarray) -> np.ndarray:
        return cv2.resize(np.asarray(img, np.float32), (w, h), interpolation=cv2.INTER_AREA)

    def down_object(view: int) -> tuple[np.ndarray, np.ndarray]:
        """Coarse grey averaged over object pixels only (a silhouette blended with the
        background would be matched as texture), and the coarse mask."""
        m = scene.masks[view] if scene.masks is not None else np.ones((H, W), bool)
        cover = down(m)
        return down(grey[view] * m) / np.maximum(cover, 1e-6), cover

    K = [geometry.scale_intrinsics(k, sx, sy) for k in scene.K]
    ref_img, ref_cover = down_object(ref)
    ref_mask = ref_cover > 0.5
    if not ref_mask.any():
        return out
    gy, gx = np.nonzero(ref_mask)
    pix = np.stack([gx, gy], 1).astype(np.float64)
    near, far = sphere_depth_range(K[ref], scene.world_to_cam[ref], scene.norm_to_world, pix, params.sphere_margin)
    hit = np.isfinite(near)
    if not hit.any():
        return out
    z_near, z_far = float(near[hit].min()), float(far[hit].max())
    warps = [_relative_warp(K[ref], scene.world_to_cam[ref], K[s], scene.world_to_cam[s]) for s in srcs]
    D = _plane_count(warps, pix[hit], z_near, z_far, 1.0, params.max_depths)
    inv_planes = np.linspace(1.0 / z_far, 1.0 / z_near, D)

    k = params.fill_window
    src_data = [down_object(s) for s in srcs]
    M = ref_mask.astype(np.float32)
    neg_cost = np.empty((D, h, w), np.float32)
    e3 = np.array([0.0, 0.0, 1.0])
    for d, inv_z in enumerate(inv_planes):
        err = np.zeros((h, w), np.float32)
        n_src = np.zeros((h, w), np.float32)
        for (A, b), (img, smask) in zip(warps, src_data):
            Hm = A + np.outer(b, e3) * inv_z  # reference pixel -> source pixel on this plane
            flags = cv2.WARP_INVERSE_MAP
            warped = cv2.warpPerspective(img, Hm, (w, h), flags=cv2.INTER_LINEAR | flags)
            seen = cv2.warpPerspective(smask, Hm, (w, h), flags=cv2.INTER_LINEAR | flags, borderValue=0.0) > 0.99
            both = M * seen
            cover = box_mean(both, k)
            diff = box_mean(both * (warped - ref_img) ** 2, k)
            ok = cover > 0.5  # the source sees most of the window on its object
            err += np.where(ok, diff / np.maximum(cover, 1e-6), 0.0)
            n_src += ok
        neg_cost[d] = np.where(n_src == len(srcs), -err / len(srcs), -np.inf)
    neg_cost = np.maximum(neg_cost, -1e6)  # finite for the parabola; such winners fail the rms test
    best, best_neg, offset, interior = _peak(neg_cost)
    rms = np.sqrt(np.maximum(-best_neg, 0.0))
    # A window of one grey (no shading either) fits every depth; its winner is noise.
    frac = box_mean(M, k)
    with np.errstate(invalid="ignore", divide="ignore"):
        mu = box_mean(M * ref_img, k) / frac
        std = np.sqrt(np.maximum(box_mean(M * ref_img * ref_img, k) / frac - mu * mu, 0.0))
    ok = ref_mask & interior & (rms <= params.fill_max_rms) & (std >= params.fill_min_std)
    step = (inv_planes[-1] - inv_planes[0]) / (D - 1)
    inv_depth = np.where(ok, inv_planes[best] + offset * step, 0.0).astype(np.float32)
    score = np.where(ok, 1.0 - rms / params.fill_max_rms, 0.0).astype(np.float32)

    # Back to full size: keep a pixel only where every coarse sample under it was valid.
    full = (W, H)
    support = cv2.resize(ok.astype(np.float32), full, interpolation=cv2.INTER_LINEAR)
    inv_full = cv2.resize(inv_depth, full, interpolation=cv2.INTER_LINEAR)
    keep = todo & mask & (support > 0.999) & (inv_full > 0)
    out.depth_mm[keep] = 1.0 / inv_full[keep]
    out.score[keep] = cv2.resize(score, full, interpolation=cv2.INTER_LINEAR)[keep]
    out.valid[:] = keep
    out.num_depths = D
    return out


def run(scene: Scene, cfg: InitConfig) -> InitResult:
    """The ``mvs`` backend: sweep every view, check consistency, fuse.

    Per-pixel confidence = max(NCC, 0) * (agreeing other views) / (N - 1).
    """
    grey = normalised_grey(scene.images, scene.masks)
    sweeps = [sweep_view(scene, r, cfg.mvs, grey) for r in range(scene.num_views)]
    if cfg.mvs.fill_width > 0:
        grey_abs = common_grey(scene.images, scene.masks)
        sweeps = [_merge(sw, sweep_plain(scene, r, cfg.mvs, grey_abs, _masks(scene)[r] & ~sw.valid))
                  for r, sw in enumerate(sweeps)]
    depths = np.stack([s.depth_mm for s in sweeps])
    valid = np.stack([s.valid for s in sweeps])
    views = check_consistency(depths, valid, scene.K, scene.world_to_cam, scene.images, cfg.consistency)
    n_other = max(scene.num_views - 1, 1)
    maps, point_conf = [], []
    for i, (sw, vp) in enumerate(zip(sweeps, views)):
        conf = np.clip(sw.score, 0.0, 1.0) * vp.count / n_other
        maps.append(DepthMap(scene.view_ids[i], np.where(vp.valid, sw.depth_mm, 0.0).astype(np.float32),
                             np.where(vp.valid, conf, 0.0).astype(np.float32),
                             vp.valid, scene.K[i], scene.world_to_cam[i]))
        point_conf.append(conf[vp.pixels[:, 0], vp.pixels[:, 1]])
    masks = _masks(scene)
    filled_px = []
    if cfg.mvs.hole_fill_area > 0:
        all_depths = [m.depth_mm for m in maps]
        filled = [filled_hole_points(scene, i, m, vp.valid, cfg.mvs.hole_fill_area, cfg.mvs.hole_fill_max_bend,
                                     all_depths) for i, (m, vp) in enumerate(zip(maps, views))]
        filled_px = [len(f.pixels) for f in filled]
        views, point_conf = views + filled, point_conf + [np.zeros(len(f.pixels)) for f in filled]
        cams = np.concatenate([scene.world_to_cam, scene.world_to_cam])
    else:
        cams = scene.world_to_cam
    cloud = fuse_views(views, point_conf, cams, cfg.voxel_norm * scene.norm_scale_mm, cfg.normal_knn)
    matched = [round(float(s.valid.sum() / max(1, m.sum())), 4) for s, m in zip(sweeps, masks)]
    consistent = [round(float(v.valid.sum() / max(1, m.sum())), 4) for v, m in zip(views, masks)]
    info = {
        "num_depths": [s.num_depths for s in sweeps],
        "matched_fraction": matched,
        "consistent_fraction": consistent,
        "hole_filled_pixels": filled_px,
        "warnings": match_warnings(scene.view_ids, matched, consistent, cfg.mvs),
    }
    return InitResult(cloud, maps, info)


DISAGREE_REL = 0.005  # another view's depth this far (relative) from a filled point contradicts it


def filled_hole_points(scene: Scene, i: int, depth: DepthMap, consistent: np.ndarray, max_area: float,
                       max_bend: float, all_depths: list[np.ndarray]) -> ViewPoints:
    """View ``i``'s enclosed holes of the consistent depth (at most ``max_area`` of the image's
    pixels each, inside the view's mask when the scene has masks, with a rim within
    ``max_bend`` of a plane, and no other view's depth in ``all_depths`` off any filled point), filled by harmonic interpolation, as points (world mm) with the view's colours;
    ``count`` 0: no other view confirms them."""
    H, W = consistent.shape
    mask = scene.masks[i] if scene.masks is not None else None
    c2w = geometry.rigid_inverse(scene.world_to_cam[i])
    ys, xs = np.mgrid[0:H, 0:W]
    cam_points = geometry.pixel_rays(scene.K[i], xs, ys) * depth.depth_mm[..., None].astype(np.float64)
    holes = flat_rimmed(enclosed_holes(consistent, int(max_area * H * W), mask), cam_points, max_bend)
    z = harmonic_fill(depth.depth_mm, holes)
    rows, cols = np.nonzero(holes)
    rays = geometry.pixel_rays(scene.K[i], cols, rows)
    pts = (rays * z[rows, cols][:, None]) @ c2w[:3, :3].T + c2w[:3, 3]
    others = [j for j in range(scene.num_views) if j != i]
    bad = contradicted(pts, [all_depths[j] for j in others], scene.K[others], scene.world_to_cam[others],
                           DISAGREE_REL)
    if bad.any():  # a hole another view sees into or past is a gap or a recess, not a surface: left open
        labels, _ = ndimage.label(holes, structure=np.ones((3, 3)))
        open_labels = np.unique(labels[rows[bad], cols[bad]])
        holes &= ~np.isin(labels, open_labels)
        keep = holes[rows, cols]
        rows, cols, pts = rows[keep], cols[keep], pts[keep]
    return ViewPoints(holes, np.zeros((H, W), np.int64), pts, scene.images[i][rows, cols].astype(np.float32),
                      np.stack([rows, cols], 1))


def match_warnings(view_ids: list[int], matched: list[float], consistent: list[float], params: MVSConfig) -> list[str]:
    """One message per view whose matched or consistent fraction of mask pixels is below
    ``params.warn_below_matched`` / ``warn_below_consistent``: such a run exits normally
    but its cloud covers little of the object (a real dark, wide-baseline scan: 5-10 %
    matched, 2-5 % consistent; scan24: 90-95 % and 77-84 %)."""
    out = []
    for v, m, c in zip(view_ids, matched, consistent):
        low = []
        if m < params.warn_below_matched:
            low.append(f"matched {m:.1%} (init.mvs.warn_below_matched {params.warn_below_matched:.0%})")
        if c < params.warn_below_consistent:
            low.append(f"consistent {c:.1%} (init.mvs.warn_below_consistent {params.warn_below_consistent:.0%})")
        if low:
            out.append(f"view {v}: only {' and '.join(low)} of its mask pixels: the cloud misses much of the "
                       "object there; check the mask, the exposure and the baseline to the other views")
    return out


def _merge(ncc: SweepResult, fill: SweepResult) -> SweepResult:
    """NCC depths where they are valid, the plain-region fill elsewhere."""
    use = fill.valid & ~ncc.valid
    return SweepResult(np.where(use, fill.depth_mm, ncc.depth_mm), np.where(use, fill.score, ncc.score),
                       ncc.valid | use, ncc.num_depths)


def _masks(scene: Scene) -> np.ndarray:
    return scene.masks if scene.masks is not None else np.ones(scene.images.shape[:3], bool)
