"""The DTU Chamfer protocol of the public evaluation script (2DGS / NeuS / SparseNeuS).

Step by step (distances in mm):

1. Optional culling: project the mesh vertices into the chosen views; a vertex is kept iff,
   in every view where it projects strictly inside the image (``0 < x < W-1``,
   ``0 < y < H-1``, in front of the camera), the mask dilated by a disk of radius
   ``mask_dilation_px * W / 1600`` is set at the nearest pixel. A triangle is kept iff its
   three vertices are.
2. Data points: the kept vertices plus a ``sample_spacing_mm`` grid on every triangle;
   greedy radius downsampling at ``downsample_radius_mm`` in a random (seeded) order.
3. ``data_in``: points with ``BB[0] - patch <= p < BB[1] + 2 patch``; ``data_in_obs``: those
   whose ObsMask voxel ``round((p - BB[0]) / Res)`` is inside the volume and set.
4. Accuracy: nearest GT point (all stl points) of each ``data_in_obs`` point.
5. Completeness: nearest ``data_in`` point of each GT point above the ground plane.
6. Each mean is over distances ``< max_dist_mm`` (larger ones are left out, not clamped);
   overall = (accuracy + completeness) / 2.

A direction with no distance below ``max_dist_mm`` (e.g. a mesh far from the object) has an
undefined mean: it is reported as NaN (``null`` in JSON) with ``valid = False`` and a line
in ``problems``, never as a number.
"""
from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pipeline import atomic, geometry
from pipeline.config.evaluate import EvaluateConfig
from pipeline.evaluation.gt import GroundTruth, read_mesh
from pipeline.evaluation.record import distance_band_key
from pipeline.evaluation.sampling import check_mesh, radius_downsample, sample_mesh
from pipeline.evaluation.seen import InputView, accuracy_by_views_seen, completeness_by_views_seen

# The script's masks are 1600 px wide; its 24 px dilation is scaled to other widths.
REFERENCE_MASK_WIDTH_PX = 1600


@dataclass
class CullView:
    """One view used for culling: camera at the mask's resolution and its (undilated) mask."""

    view_id: int
    K: np.ndarray  # 3x3, pixels of ``mask``
    world_to_cam: np.ndarray  # 4x4, world mm -> camera
    mask: np.ndarray  # (H, W) bool


def dilate_mask(mask: np.ndarray, radius_px: float) -> np.ndarray:
    """Binary dilation by the disk ``{(dx, dy): dx^2 + dy^2 <= radius^2}`` (skimage's ``disk``)."""
    r = int(math.floor(radius_px))
    if r <= 0:
        return mask.astype(bool)
    yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
    disk = (xx**2 + yy**2 <= radius_px**2).astype(np.uint8)
    return cv2.dilate(mask.astype(np.uint8), disk, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


def cull_vertices(vertices_mm: np.ndarray, views: list[CullView], dilation_px_at_1600: float) -> np.ndarray:
    """Bool keep-mask over the vertices (step 1 of the protocol)."""
    # Per-coordinate arithmetic instead of (N, 3) @ (3, 3): BLAS threads on tall-skinny
    # products are slow when the two cores are shared (seen: 1 s vs 0.03 s per 1 M points).
    x, y, z = (np.ascontiguousarray(vertices_mm[:, k], dtype=np.float64) for k in range(3))
    keep = np.ones(len(vertices_mm), bool)
    for v in views:
        H, W = v.mask.shape
        dilated = dilate_mask(v.mask, dilation_px_at_1600 * W / REFERENCE_MASK_WIDTH_PX)
        P = v.K @ v.world_to_cam[:3]  # world mm -> homogeneous pixels; row 2 gives the depth
        uh, vh, d = (P[r, 0] * x + P[r, 1] * y + P[r, 2] * z + P[r, 3] for r in range(3))
        with np.errstate(divide="ignore", invalid="ignore"):
            px, py = uh / d, vh / d
            # Points behind the camera have no meaningful pixel; they do not vote (the
            # script, written for DTU's object-centred views, never meets them).
            inside = (d > 0) & (px > 0) & (px < W - 1) & (py > 0) & (py < H - 1)
        # Nearest pixel (integer pixel centres), like grid_sample(mode="nearest").
        in_mask = np.zeros(len(vertices_mm), bool)
        in_mask[inside] = dilated[np.rint(py[inside]).astype(np.int64), np.rint(px[inside]).astype(np.int64)]
        keep &= ~inside | in_mask
    return keep


def load_cull_views(scene_dir: str | Path, mode: str, input_views: list[int] | tuple[int, ...]) -> list[CullView]:
    """Culling views of a DTU-layout scene: ``input`` (``input_views``), ``all`` (every view
    with a camera and a mask) or ``none``. Cameras are scaled to the mask resolution when
    the masks are stored at another size than the images."""
    from pipeline.data import dtu

    if mode == "none":
        return []
    if mode not in ("input", "all"):
        raise ValueError(f"cull mode must be input, all or none, got {mode!r}")
    root = Path(scene_dir)
    cams = dtu.load_cameras(root)
    masks = dtu.load_masks(root, None if mode == "all" else list(input_views))
    ids = sorted(v for v in masks if v in cams.K) if mode == "all" else list(input_views)
    missing = [v for v in ids if v not in cams.K]
    if missing:
        raise dtu.SceneError(f"{cams.path}: no camera for culling view(s) {missing}")
    if not ids:
        raise dtu.SceneError(f"{root}: no view has both a camera and a mask; cannot cull (use --cull none)")
    try:
        img_w, img_h = dtu.stored_image_size(root)
    except dtu.SceneError:  # no images: masks are taken to be at the cameras' resolution
        img_w = img_h = None
    views = []
    for v in ids:
        H, W = masks[v].shape
        K = cams.K[v]
        if img_w is not None and (W, H) != (img_w, img_h):
            K = geometry.scale_intrinsics(K, W / img_w, H / img_h)
        views.append(CullView(view_id=v, K=K, world_to_cam=cams.world_to_cam[v], mask=masks[v]))
    return views


def submesh(vertices: np.ndarray, triangles: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kept vertices and the triangles whose three vertices are kept (re-indexed)."""
    new_index = np.cumsum(keep) - 1
    tri = triangles[keep[triangles].all(axis=1)]
    return vertices[keep], new_index[tri]


def _kdtree(points: np.ndarray) -> cKDTree:
    # Unbalanced, non-compact trees build several times faster and query about as fast.
    return cKDTree(points, leafsize=16, balanced_tree=False, compact_nodes=False)


def _nn_distances(query: np.ndarray, ref: np.ndarray, max_dist: float) -> np.ndarray:
    """Distance from each query point to its nearest ``ref`` point; ``inf`` when it is
    ``max_dist`` or more (those are left out of the means anyway) or ``ref`` is empty."""
    if len(query) == 0:
        return np.zeros(0)
    if len(ref) == 0:
        return np.full(len(query), np.inf)
    d, _ = _kdtree(ref).query(query, k=1, distance_upper_bound=max_dist, workers=-1)
    return d


def _mean_below(d: np.ndarray, max_dist: float) -> tuple[float, int, float]:
    """(mean of d < max_dist, how many, fraction of d left out); NaNs when undefined."""
    used = d < max_dist
    n = int(used.sum())
    mean = float(d[used].mean()) if n else math.nan
    frac_out = float(1.0 - n / len(d)) if len(d) else math.nan
    return mean, n, frac_out


# Edges (mm) of the bands ``by_distance`` splits a mean into; the last band ends at max_dist.
DISTANCE_BANDS_MM = (0.0, 0.5, 1.0, 2.0, 5.0)


def by_distance(d: np.ndarray, max_dist: float, edges: tuple[float, ...] = DISTANCE_BANDS_MM) -> dict:
    """Split the mean of ``d < max_dist`` by distance band: for each band ``[lo, hi)``, the
    fraction of the used distances in it and its share of the mean (``sum over the band /
    number used``; the shares add up to the mean). Tells a tail of far-off points (which a
    filter could remove) from a small offset everywhere (which only better geometry fixes)."""
    used = d[d < max_dist]
    uppers = [*edges[1:], max_dist]
    out = {}
    for lo, hi in zip(edges, uppers):
        if lo >= max_dist:
            break
        band = used[(used >= lo) & (used < hi)]
        key = distance_band_key(lo, min(hi, max_dist))
        out[key] = {"fraction": len(band) / len(used) if len(used) else math.nan,
                    "share_mm": float(band.sum() / len(used)) if len(used) else math.nan}
    return out


def evaluate_mesh(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    gt: GroundTruth,
    cfg: EvaluateConfig,
    views: list[CullView] | None = None,
    seed: int = 0,
    log: Callable[[str], None] | None = print,
    name: str = "mesh",
    seen_views: list[InputView] | None = None,
) -> dict:
    """DTU Chamfer distance of a mesh in world millimetres against ``gt``.

    ``views``: the culling views (``None`` or empty: no culling). ``seed`` fixes the
    downsampling order (synthetic GT points are thinned in an order derived from their
    own seed, never this one: see ``gt.GT_SEED_PURPOSE``). ``log`` receives progress lines (``None``: silent).
    ``seen_views``: the input cameras; with a GT mesh (synthetic scenes) the result also has
    ``accuracy_by_views_seen`` and ``completeness_by_views_seen`` (:mod:`pipeline.evaluation.seen`). Raises
    :class:`~pipeline.evaluation.sampling.MeshError` for an empty or degenerate mesh.

    Returns a JSON-ready dict: ``accuracy_mm``, ``completeness_mm``, ``overall_mm`` (NaN when
    undefined), ``valid``, ``problems``, ``counts``, ``fraction_beyond_max_dist``,
    ``accuracy_by_distance`` and ``completeness_by_distance`` (:func:`by_distance`),
    ``timings_s`` and ``config``.
    """
    say = log or (lambda _msg: None)
    timings: dict[str, float] = {}
    t_all = t = time.perf_counter()

    def lap(key: str) -> float:
        nonlocal t
        now = time.perf_counter()
        timings[key] = round(now - t, 3)
        t = now
        return timings[key]

    V, F = check_mesh(vertices_mm, triangles, name=name)
    lap("check")
    counts = {"mesh_vertices": len(V), "mesh_triangles": len(F)}
    problems: list[str] = []
    if views:
        keep = cull_vertices(V, views, cfg.mask_dilation_px)
        V, F = submesh(V, F, keep)
        say(f"[evaluate] culled by views {[v.view_id for v in views]}: kept {len(V)}/{counts['mesh_vertices']} "
            f"vertices, {len(F)}/{counts['mesh_triangles']} triangles ({lap('cull'):.1f} s)")
        if len(V) == 0:
            problems.append("culling removed every vertex: the mesh lies outside the (dilated) masks")
    counts.update(culled_vertices=len(V), culled_triangles=len(F))

    data = sample_mesh(V, F, cfg.sample_spacing_mm)
    counts["data_sampled"] = len(data)
    say(f"[evaluate] sampled {len(data)} points at {cfg.sample_spacing_mm} mm ({lap('sample'):.1f} s)")
    data = data[radius_downsample(data, cfg.downsample_radius_mm, seed=seed)]
    counts["data_downsampled"] = len(data)
    say(f"[evaluate] downsampled to {len(data)} points, radius {cfg.downsample_radius_mm} mm "
        f"({lap('downsample'):.1f} s)")

    inbound, in_obs = gt.box_and_observed(data, cfg.patch_mm)
    data_in = data[inbound]
    data_in_obs = data_in[in_obs]
    counts.update(data_in_bb=len(data_in), data_in_obs=len(data_in_obs))
    say(f"[evaluate] {len(data_in)} points in the bounding box (+patch), {len(data_in_obs)} in the observation "
        f"mask ({lap('mask'):.1f} s)")
    if len(data) and not len(data_in):
        ext = float(np.ptp(data, axis=0).max())
        hint = " (is it in the normalised frame instead of world mm?)" if ext < 10 else ""
        problems.append(f"no data point inside the GT bounding box + patch; mesh extent {ext:.3g} mm{hint}")

    max_dist = cfg.max_dist_mm
    d_acc = _nn_distances(data_in_obs, gt.points_mm, max_dist)
    acc, n_acc, out_acc = _mean_below(d_acc, max_dist)
    say(f"[evaluate] accuracy: {len(d_acc)} data points -> {len(gt.points_mm)} GT points ({lap('accuracy'):.1f} s)")
    by_seen = gt_mesh = None
    if seen_views and (gt.root / "mesh.ply").is_file():
        gt_mesh = read_mesh(gt.root / "mesh.ply")
        by_seen = accuracy_by_views_seen(data_in_obs, gt.points_mm, *gt_mesh, seen_views, max_dist)
        say("[evaluate] accuracy by input views seeing the surface: " + ", ".join(
            f"{g}: {100 * r['fraction']:.1f}% at {r['accuracy_mm']:.3f} mm" for g, r in by_seen.items())
            + f" ({lap('seen'):.1f} s)")
    gt_above = gt.points_mm[gt.above_plane(gt.points_mm)]
    d_comp = _nn_distances(gt_above, data_in, max_dist)
    comp, n_comp, out_comp = _mean_below(d_comp, max_dist)
    say(f"[evaluate] completeness: {len(gt_above)} GT points above the plane -> {len(data_in)} data points "
        f"({lap('completeness'):.1f} s)")
    comp_by_seen = None
    if gt_mesh is not None:
        comp_by_seen = completeness_by_views_seen(gt_above, d_comp, *gt_mesh, seen_views, max_dist)
        say("[evaluate] completeness by input views seeing the GT point: " + ", ".join(
            f"{g}: {100 * r['fraction']:.1f}% at {r['completeness_mm']:.3f} mm" for g, r in comp_by_seen.items())
            + f" ({lap('seen_completeness'):.1f} s)")
    counts.update(gt_points=len(gt.points_mm), gt_above_plane=len(gt_above), accuracy_used=n_acc,
                  completeness_used=n_comp)
    if n_acc == 0:
        problems.append(f"accuracy undefined: none of {len(d_acc)} observed data points is within {max_dist} mm "
                        "of the GT")
    if n_comp == 0:
        problems.append(f"completeness undefined: none of {len(gt_above)} GT points is within {max_dist} mm "
                        "of the data")
    overall = (acc + comp) / 2
    timings["total"] = round(time.perf_counter() - t_all, 3)
    for p in problems:
        say(f"[evaluate] warning: {p}")
    say(f"[evaluate] accuracy {acc:.4f} mm, completeness {comp:.4f} mm, overall {overall:.4f} mm "
        f"({timings['total']:.1f} s)")
    return {
        "accuracy_mm": acc,
        "completeness_mm": comp,
        "overall_mm": overall,
        "valid": not math.isnan(overall),
        "problems": problems,
        "scan_id": gt.scan_id,
        "counts": counts,
        "fraction_beyond_max_dist": {"accuracy": out_acc, "completeness": out_comp},
        "accuracy_by_distance": by_distance(d_acc, max_dist),
        "completeness_by_distance": by_distance(d_comp, max_dist),
        **({"accuracy_by_views_seen": by_seen} if by_seen is not None else {}),
        **({"completeness_by_views_seen": comp_by_seen} if comp_by_seen is not None else {}),
        "timings_s": timings,
        "config": {**dataclasses.asdict(cfg), "seed": seed,
                   "cull_view_ids": [v.view_id for v in views] if views else []},
    }


def _json_ready(obj):
    if isinstance(obj, float) and not math.isfinite(obj):
        return None  # JSON has no NaN; null plus "valid": false says it is undefined
    if isinstance(obj, dict):
        return {k: _json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_ready(v) for v in obj]
    if isinstance(obj, np.generic):
        return _json_ready(obj.item())
    return obj


def write_metrics(path: str | Path, metrics: dict) -> None:
    """Write metrics as JSON (NaN -> null) atomically (temp file in the same folder, renamed)."""
    atomic.write_text(path, json.dumps(_json_ready(metrics), indent=2, allow_nan=False) + "\n")
