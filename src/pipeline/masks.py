"""Object masks derived per input view for captures without masks (issues 58, 77).

One decision in 3D, projected into every view: :func:`pipeline.labelling.label_scene` labels
the init's depth points of all views at once as object, support or background, and each
view's mask starts from that labelling's projection. An image refinement may move the mask's boundary only within a band
around it, and a self-check compares every mask with the labelling before it is kept.

Steps (:func:`derive_masks`), per view:

1. **Projection** (:func:`projected_object`): the view's own depth pixels labelled object,
   and every other view's object points that land in this view unoccluded; closed over
   ``closing_share`` of the image's longer side (the splats of other views, a textureless
   part MVS matched at a few pixels only) and with enclosed holes filled unless most of
   the depth there says support or background (the table seen through a handle).
2. **Refinement in a band** of ``band_share`` of the longer side around the projection's
   boundary: outside the band sure background, deeper inside sure foreground (but for depth
   labelled support or background, which stays probable background: the table seen through
   a handle). Beyond the band, background needs evidence: depth labelled support or
   background, or a ray that other views look through (:func:`refuted_rays`); a pixel with
   neither (a part only this view matched, or none did) stays probable background for the
   refinement to decide by its colour. Inside the band OpenCV's GrabCut (``GC_INIT_WITH_MASK``) decides, or, with a
   salient-object model (:class:`SaliencyModel`, ``gcgs masks --model``), its map does.
3. **Cleaning**: enclosed holes without depth filled (:func:`fill_depthless_holes`), specks
   dropped (:func:`drop_small_components`).
4. **Self-check** (:func:`self_check`): every object point two views agree on and this view
   sees must lie in its mask (at least :data:`MIN_KEPT` of them), and the mask's area must
   stay within :data:`AREA_RATIO` of the projection's. A view that fails, or every view when
   the labelling found no object, gets the region's silhouette (the sphere grown to hold
   the object, cut by the support plane: never worse than no masks) with one warning naming
   the view and the failed test.

Deterministic: OpenCV's RNG is seeded before every GrabCut call and the labelling's RANSAC
and samples are seeded.

Frames and units (:mod:`pipeline.geometry`): world frame in mm; ``world_to_cam`` is a 4x4
rigid world mm -> OpenCV camera transform; ``K`` is 3x3 for the image's own size with pixel
centres at integer coordinates; depth maps are camera-frame z in mm with 0 = no depth;
images are ``(H, W, 3)`` float RGB in [0, 1]; masks are ``(H, W)`` bool, True on the object.
A ray's parameter ``t`` is its camera depth (directions have camera-frame z = 1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import scipy.ndimage

from pipeline import geometry
from pipeline import labelling
from pipeline.labelling import SceneLabels
from pipeline.meshing.region import Region

GC_BGD, GC_FGD, GC_PR_BGD, GC_PR_FGD = cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_BGD, cv2.GC_PR_FGD
# Brightness normalisation before 8-bit quantisation: this percentile of the image maps to 1
# (a dark capture keeps its contrast for GrabCut's colour models).
BRIGHTNESS_PERCENTILE = 99.0
# Self-check: a mask keeps at least this share of the object points two views agree on that
# land unoccluded in its view, within SELF_CHECK_TOLERANCE_PX (GrabCut trims thin parts at the
# boundary by a few %; a mask that lost the object, as per-view decisions did on a real
# capture, keeps far fewer) ...
MIN_KEPT = 0.8
SELF_CHECK_TOLERANCE_PX = 2
# ... and its area stays within these factors of the projected object's.
AREA_RATIO = (1.0 / 3.0, 3.0)
# Free space along a pixel's ray (:func:`refuted_rays`): a grid of this step, rays sampled so often.
RAY_STEP_PX = 4
RAY_SAMPLES = 16
# Overlays (:func:`overlay`): the outside of a mask at this share of its brightness, the
# contour in a colour rare in photos of objects.
OVERLAY_OUTSIDE_GAIN = 0.3
OVERLAY_CONTOUR_RGB = (255, 0, 255)


@dataclass
class ViewMask:
    """One view's derived mask and how it was made."""

    view: int  # the view id (as given to derive_masks)
    mask: np.ndarray  # (H, W) bool: the object
    coverage: float  # mask.mean()
    method: str  # "grabcut" | "model" | "projection" (nothing to refine) | "fallback_region"
    warnings: list[str] = field(default_factory=list)
    facts: dict = field(default_factory=dict)  # pixel counts, coverages per step, seconds
    stages: dict = field(default_factory=dict)  # (H, W) bool masks after each step: projection, refined, cleaned


# ---------------------------------------------------------------------------------------
# The region along a pixel's ray


def pixel_ray_dirs(K: np.ndarray, world_to_cam: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(origin (3,), dirs (H, W, 3))``: world-frame rays through every pixel centre with
    camera-frame z = 1, so the ray parameter of a point is its camera depth (mm)."""
    dirs = geometry.pixel_rays(K, shape=shape) @ np.asarray(world_to_cam, np.float64)[:3, :3]  # R^T d
    return geometry.camera_center(world_to_cam), dirs


def ray_intervals(region: Region, origin: np.ndarray, dirs: np.ndarray,
                  parts: str = "all") -> tuple[np.ndarray, np.ndarray]:
    """``(t_near, t_far)`` (shape ``dirs.shape[:-1]``): the stretch of each ray
    ``origin + t dirs`` (``t >= 0``) inside ``region``, empty where ``t_far <= t_near``.
    ``parts``: ``all`` (the whole region), ``no_footprint`` (the sphere above the plane) or
    ``sphere``. The region is convex (a sphere cut by half-spaces), so the stretch is one
    interval: the sphere's, clipped by the half-space above the plane (+ margin) and by each
    footprint edge's vertical half-space (see :meth:`Region.contains`)."""
    if parts not in ("all", "no_footprint", "sphere"):
        raise ValueError(f"ray_intervals: parts must be all, no_footprint or sphere, got {parts!r}")
    o = np.asarray(origin, np.float64)
    d = np.asarray(dirs, np.float64)
    oc = o - region.centre_mm
    a = np.einsum("...i,...i->...", d, d)
    b = 2.0 * (d @ oc)
    c = float(oc @ oc) - region.radius_mm ** 2
    disc = b * b - 4.0 * a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t0 = np.maximum((-b - sq) / (2.0 * a), 0.0)
    t1 = np.where(disc >= 0, (-b + sq) / (2.0 * a), -np.inf)

    def clip(w: np.ndarray, limit: float, t0: np.ndarray, t1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Keep w . (o + t d) <= limit.
        wd, wo = d @ w, float(w @ o)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (limit - wo) / wd
        t1 = np.where(wd > 0, np.minimum(t1, t), t1)
        t0 = np.where(wd < 0, np.maximum(t0, t), t0)
        if wo > limit:  # rays parallel to the boundary from outside it
            t1 = np.where(wd == 0, -np.inf, t1)
        return t0, t1

    if parts != "sphere" and region.plane is not None:
        n, d0 = region.plane[:3], float(region.plane[3])
        t0, t1 = clip(-n, d0 - region.margin_mm, t0, t1)  # n . x + d0 > margin
        if parts == "all" and region.footprint is not None:
            for a_x, a_y, e_b in region.footprint:
                w = a_x * region.plane_axes[0] + a_y * region.plane_axes[1]
                t0, t1 = clip(w, region.footprint_margin_mm - e_b, t0, t1)
    return t0, t1


def silhouette(region: Region, K: np.ndarray, world_to_cam: np.ndarray, shape: tuple[int, int],
               parts: str = "all") -> np.ndarray:
    """``(H, W)`` bool: the pixels whose centre ray crosses ``region`` (``parts``: see
    :func:`ray_intervals`)."""
    t0, t1 = ray_intervals(region, *pixel_ray_dirs(K, world_to_cam, shape), parts=parts)
    return t1 > t0


def to_uint8(image: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` float [0, 1] -> 8-bit BGR for OpenCV, stretched so the
    ``BRIGHTNESS_PERCENTILE`` of the image maps to 255."""
    img = np.asarray(image, np.float64)
    top = float(np.percentile(img, BRIGHTNESS_PERCENTILE))
    img = img / top if top > 1e-6 else img
    return np.ascontiguousarray(np.clip(np.round(img[..., ::-1] * 255.0), 0, 255).astype(np.uint8))


def grabcut(image: np.ndarray, labels: np.ndarray, iterations: int, max_side: int, seed: int) -> np.ndarray | None:
    """Foreground ``(H, W)`` bool of GrabCut seeded with ``labels`` (module docstring,
    step 2). Sure labels of ``labels`` are kept as given. ``None`` when the (downscaled)
    labels hold no foreground or no background: nothing for GrabCut to learn."""
    H, W = labels.shape
    img = to_uint8(image)
    lab = labels
    scale = min(1.0, max_side / max(H, W))
    if scale < 1.0:
        size = (max(1, round(W * scale)), max(1, round(H * scale)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        lab = cv2.resize(labels, size, interpolation=cv2.INTER_NEAREST)
    lab = np.ascontiguousarray(lab.copy())
    fg_lab = (lab == GC_FGD) | (lab == GC_PR_FGD)
    if fg_lab.all() or not fg_lab.any():  # GrabCut needs samples of both (the downscaled seed may lose a speck)
        return None
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    cv2.setRNGSeed(int(seed))
    lab, _, _ = cv2.grabCut(img, lab, None, bgd, fgd, int(iterations), cv2.GC_INIT_WITH_MASK)
    fg = ((lab == GC_FGD) | (lab == GC_PR_FGD)).astype(np.float32)
    if scale < 1.0:
        fg = cv2.resize(fg, (W, H), interpolation=cv2.INTER_LINEAR)
    out = fg > 0.5
    out[labels == GC_BGD] = False
    out[labels == GC_FGD] = True
    return out


def fill_depthless_holes(mask: np.ndarray, labels: np.ndarray, depth_mm: np.ndarray, max_depth_share: float) -> np.ndarray:
    """``mask`` with its enclosed holes (4-connected background not touching the image border)
    filled where the hole holds no sure-background seed label and at most
    ``max_depth_share`` of its pixels have depth the seed calls background (probable or
    sure): a textureless part MVS left without depth but for a few matches on the object,
    which GrabCut took for background by its colour. A hole showing the table or anything
    else outside the region through the object has background depth there and stays open;
    one showing a backdrop without any depth is filled (the cost of this step)."""
    lab, n = scipy.ndimage.label(~mask)
    if n == 0:
        return mask.copy()
    border = np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))
    size = np.bincount(lab.ravel(), minlength=n + 1)
    sure_bg = np.bincount(lab.ravel(), weights=(labels == GC_BGD).ravel(), minlength=n + 1)
    background_depth = (depth_mm > 0) & ((labels == GC_BGD) | (labels == GC_PR_BGD))
    with_depth = np.bincount(lab.ravel(), weights=background_depth.ravel(), minlength=n + 1)
    fill = (sure_bg == 0) & (with_depth <= max_depth_share * size)
    fill[0] = False
    fill[border] = False
    return mask | fill[lab]


def drop_small_components(mask: np.ndarray, min_fraction: float) -> np.ndarray:
    """``mask`` without the 8-connected components smaller than ``min_fraction`` of its largest."""
    lab, n = scipy.ndimage.label(mask, structure=np.ones((3, 3)))
    if n <= 1:
        return mask.copy()
    sizes = np.bincount(lab.ravel())[1:]
    keep = np.zeros(n + 1, bool)
    keep[1:] = sizes >= min_fraction * sizes.max()
    return keep[lab]


def overlay(image: np.ndarray, mask: np.ndarray, outside_gain: float = OVERLAY_OUTSIDE_GAIN) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB picture of ``mask`` over ``image`` (float RGB in [0, 1]) for a
    person to judge at a glance: the image's brightness stretched as GrabCut saw it
    (:func:`to_uint8`), the outside of the mask darkened to ``outside_gain`` and the
    mask's contour drawn in :data:`OVERLAY_CONTOUR_RGB`, 1 px wide per 400 px of the longer side."""
    img = to_uint8(image)[..., ::-1].astype(np.float64)  # back to RGB
    m = np.asarray(mask, bool)
    img[~m] *= outside_gain
    out = np.ascontiguousarray(np.clip(np.round(img), 0, 255).astype(np.uint8))
    contours, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, OVERLAY_CONTOUR_RGB, max(1, round(max(m.shape) / 400)))
    return out




# ---------------------------------------------------------------------------------------
# The labelling projected into a view


def projected_object(i: int, labels: SceneLabels, depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
                     points: np.ndarray, point_views: np.ndarray, rel_tol: float) -> np.ndarray:
    """``(H, W)`` bool: view ``i``'s own depth pixels labelled object and the pixels where
    another view's object points (``points``, from ``point_views``) land unoccluded (view
    ``i`` has no depth there, or depth not nearer than the point by more than ``rel_tol``)."""
    shape = depths_mm[i].shape
    out = labels.pixel_labels[i] == labelling.OBJECT
    other = point_views != i
    rows, cols, z, lands = labelling.pixel_of(K[i], world_to_cam[i], points[other], shape)
    d = depths_mm[i][rows, cols]
    visible = lands & ((d <= 0) | (d >= z * (1.0 - rel_tol)))
    out[rows[visible], cols[visible]] = True
    return out


def refuted_rays(i: int, region: Region, depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
                 rel_tol: float, step_px: int = RAY_STEP_PX, samples: int = RAY_SAMPLES) -> np.ndarray:
    """``(H, W)`` bool: pixels of view ``i`` whose whole ray stretch inside ``region`` other
    views look through (free space): at every one of ``samples`` points along it some other
    view's nearest depth in the :data:`pipeline.labelling.CARVE_WINDOW` square around where
    the point lands lies beyond it by more than ``rel_tol``. Evidence of background for a
    pixel without depth of its own. Computed on a grid of ``step_px`` pixels, upsampled to
    the nearest; a ray missing the region is refuted."""
    H, W = depths_mm[i].shape
    ys, xs = np.mgrid[0:H:step_px, 0:W:step_px]
    origin = geometry.camera_center(world_to_cam[i])
    dirs = geometry.pixel_rays(K[i], xs.ravel().astype(np.float64), ys.ravel().astype(np.float64))
    dirs = dirs @ np.asarray(world_to_cam[i], np.float64)[:3, :3]
    t0, t1 = ray_intervals(region, origin, dirs, parts="no_footprint")
    frac = (np.arange(samples) + 0.5) / samples
    ts = t0[:, None] + np.maximum(t1 - t0, 0.0)[:, None] * frac
    pts = (origin + dirs[:, None, :] * ts[..., None]).reshape(-1, 3)
    refuted = np.zeros(len(pts), bool)
    for j in range(len(depths_mm)):
        if j == i:
            continue
        nearest = scipy.ndimage.minimum_filter(np.where(depths_mm[j] > 0, depths_mm[j], np.inf),
                                               size=labelling.CARVE_WINDOW)
        rows, cols, z, lands = labelling.pixel_of(K[j], world_to_cam[j], pts, (H, W))
        near = nearest[rows, cols]
        refuted |= lands & np.isfinite(near) & (near > z * (1.0 + rel_tol))
    coarse = ((t1 <= t0) | refuted.reshape(-1, samples).all(axis=1)).reshape(ys.shape)
    return np.repeat(np.repeat(coarse, step_px, axis=0), step_px, axis=1)[:H, :W]


def agreed_points(points: np.ndarray, point_views: np.ndarray, depths_mm: np.ndarray, K: np.ndarray,
                  world_to_cam: np.ndarray, rel_tol: float) -> np.ndarray:
    """``(M,)`` bool: object points that a second view confirms (its depth where the point
    lands agrees within ``rel_tol``)."""
    ok = np.zeros(len(points), bool)
    for j in range(len(depths_mm)):
        other = point_views != j
        rows, cols, z, lands = labelling.pixel_of(K[j], world_to_cam[j], points[other], depths_mm[j].shape)
        d = depths_mm[j][rows, cols]
        ok[np.flatnonzero(other)] |= lands & (d > 0) & (np.abs(d - z) <= rel_tol * z)
    return ok


def self_check(mask: np.ndarray, projection: np.ndarray, depth_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
               agreed: np.ndarray, rel_tol: float) -> tuple[str | None, dict]:
    """Step 4 of the module docstring on one view: ``(why it fails or None, facts)``.
    ``agreed``: ``(P, 3)`` object points two views agree on."""
    rows, cols, z, lands = labelling.pixel_of(K, world_to_cam, agreed, mask.shape)
    d = depth_mm[rows, cols]
    seen = lands & ((d <= 0) | (d >= z * (1.0 - rel_tol)))
    wide = scipy.ndimage.binary_dilation(mask, iterations=SELF_CHECK_TOLERANCE_PX)
    kept = float(wide[rows[seen], cols[seen]].mean()) if seen.any() else 1.0
    ratio = float(mask.sum()) / max(1.0, float(projection.sum()))
    facts = {"agreed_points_seen": int(seen.sum()), "agreed_points_kept": round(kept, 4), "area_ratio": round(ratio, 4)}
    if kept < MIN_KEPT:
        return f"the mask keeps {kept:.1%} of the {int(seen.sum())} object points two views agree on (< {MIN_KEPT:.0%})", facts
    if not AREA_RATIO[0] <= ratio <= AREA_RATIO[1]:
        return (f"the mask's area is {ratio:.2f}x the projected object's (outside "
                f"[{AREA_RATIO[0]:.2f}, {AREA_RATIO[1]:.2f}])"), facts
    return None, facts


# ---------------------------------------------------------------------------------------
# A salient-object model (gcgs masks --model)


class SaliencyModel:
    """A user-supplied salient-object or matting ONNX model (U^2-Net, IS-Net, BiRefNet
    exports): one float32 input ``1 x 3 x H x W`` (RGB, ImageNet mean/std normalisation after
    scaling the image to a maximum of 1, as U^2-Net's own pre-processing), and a first output
    ``1 x 1 x H x W`` (or ``1 x H x W``) of saliency; logits (values outside [0, 1]) pass
    through a sigmoid, and the map is min-max normalised (U^2-Net's post-processing). The
    image is resized to the model's fixed input size, or to ``size`` x ``size`` where the
    model leaves it free, and the map back to the image's size."""

    MEAN = np.array([0.485, 0.456, 0.406])
    STD = np.array([0.229, 0.224, 0.225])

    def __init__(self, path: str | Path, size: int = 320) -> None:
        import onnxruntime as ort

        from pipeline.onnx_models import ModelError, select_providers

        self.path = Path(path)
        if not self.path.is_file():
            raise ModelError(f"{self.path}: saliency model file not found")
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        try:
            self.session = ort.InferenceSession(str(self.path), sess_options=opts, providers=select_providers())
        except Exception as exc:  # onnxruntime's own exception types
            raise ModelError(f"{self.path}: not a loadable ONNX model ({type(exc).__name__}: {exc})") from exc
        inputs, outputs = self.session.get_inputs(), self.session.get_outputs()
        problems = []
        if len(inputs) != 1 or len(inputs[0].shape) != 4 or inputs[0].type != "tensor(float)":
            problems.append("it must take one float32 input of rank 4 (1 x 3 x H x W), takes "
                            + ", ".join(f"{a.name} {a.type} {a.shape}" for a in inputs))
        elif isinstance(inputs[0].shape[1], int) and inputs[0].shape[1] != 3:
            problems.append(f"its input {inputs[0].name} has {inputs[0].shape[1]} channels, not 3")
        if not outputs or len(outputs[0].shape) not in (3, 4) or outputs[0].type != "tensor(float)":
            problems.append("its first output must be float32 1 x 1 x H x W or 1 x H x W, is "
                            + (f"{outputs[0].type} {outputs[0].shape}" if outputs else "missing"))
        if problems:
            raise ModelError(f"{self.path}: not a salient-object model: " + "; ".join(problems))
        self.input_name, self.output_name = inputs[0].name, outputs[0].name
        h, w = inputs[0].shape[2:]
        self.size = (h if isinstance(h, int) else size, w if isinstance(w, int) else size)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """``(H, W)`` float saliency in [0, 1] of a float RGB image in [0, 1]."""
        from pipeline.onnx_models import ModelError

        H, W = image.shape[:2]
        x = cv2.resize(np.asarray(image, np.float32), (self.size[1], self.size[0]), interpolation=cv2.INTER_AREA)
        x = x / max(float(x.max()), 1e-6)
        x = ((x - self.MEAN) / self.STD).astype(np.float32).transpose(2, 0, 1)[None]
        try:
            out = np.asarray(self.session.run([self.output_name], {self.input_name: np.ascontiguousarray(x)})[0])
        except Exception as exc:
            raise ModelError(f"{self.path}: the saliency model failed to run: {exc}") from exc
        out = out.reshape(out.shape[-2:]) if out.size == out.shape[-1] * out.shape[-2] else None
        if out is None or not np.all(np.isfinite(out)):
            raise ModelError(f"{self.path}: the saliency model must return one finite 1 x 1 x H x W map")
        out = out.astype(np.float64)
        if out.min() < 0.0 or out.max() > 1.0:
            out = 1.0 / (1.0 + np.exp(-np.clip(out, -60.0, 60.0)))
        span = out.max() - out.min()
        out = (out - out.min()) / span if span > 1e-12 else np.zeros_like(out)
        return cv2.resize(out.astype(np.float32), (W, H), interpolation=cv2.INTER_LINEAR).astype(np.float64)


# ---------------------------------------------------------------------------------------


def derive_masks(images: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, depths_mm: np.ndarray,
                 labels: SceneLabels, view_ids: list[int] | None = None, *, band_share: float = 0.05,
                 closing_share: float = 0.01, grabcut_iterations: int = 4, grabcut_max_side: int = 400,
                 min_component_fraction: float = 0.01, hole_depth_share: float = 0.1,
                 saliency: SaliencyModel | None = None, seed: int = 0) -> list[ViewMask]:
    """Object masks of the input views of a capture without masks (module docstring).

    ``images``: ``(N, H, W, 3)`` float RGB in [0, 1]; ``K`` ``(N, 3, 3)`` at ``(H, W)``;
    ``world_to_cam`` ``(N, 4, 4)`` world mm; ``depths_mm`` ``(N, H, W)`` camera z in mm, 0 =
    no depth (the init's depth maps); ``labels``: :func:`pipeline.labelling.label_scene` of
    those depth maps; ``view_ids`` name the views in facts and warnings (default 0..N-1).

    Settings: ``band_share`` (0.02 of the longer side): how far the refinement may move the
    projection's boundary; ``closing_share`` (0.01): the projection is closed over this share
    of the longer side; ``grabcut_iterations`` (4) and ``grabcut_max_side`` (400 px: GrabCut
    runs on the image downscaled to this longer side); ``min_component_fraction`` (0.01):
    smaller components of a mask are dropped; ``hole_depth_share`` (0.1): enclosed holes with
    at most this share of background depth are filled (0: off); ``saliency``: a
    salient-object model deciding inside the band instead of GrabCut; ``seed``: OpenCV's RNG.

    Returns one :class:`ViewMask` per view, in order."""
    images = np.asarray(images)
    depths_mm = np.asarray(depths_mm, np.float64)
    n, H, W = depths_mm.shape
    if images.shape[:3] != (n, H, W) or len(K) != n or len(world_to_cam) != n or labels.pixel_labels.shape != (n, H, W):
        raise ValueError(f"derive_masks: images {images.shape}, K {np.shape(K)}, world_to_cam {np.shape(world_to_cam)}, "
                         f"depths {depths_mm.shape} and labels {labels.pixel_labels.shape} must describe the same N "
                         "views of one size")
    if not np.all(np.isfinite(depths_mm)) or np.any(depths_mm < 0):
        raise ValueError("derive_masks: depth must be finite and >= 0 (0 = no depth)")
    ids = list(range(n)) if view_ids is None else [int(v) for v in view_ids]
    rel_tol = max(labelling.MIN_REL_TOL, labelling.NOISE_K * labels.noise_rel)
    points, point_views = labels.object_points(depths_mm, K, world_to_cam)
    agreed = points[agreed_points(points, point_views, depths_mm, K, world_to_cam, rel_tol)] if n >= 2 else points
    side = max(H, W)
    band_px, closing_px = max(2, round(band_share * side)), max(1, round(closing_share * side))
    results = []
    for i in range(n):
        t = time.perf_counter()
        own = labels.pixel_labels[i]
        against = (own == labelling.SUPPORT) | (own == labelling.BACKGROUND)
        proj = projected_object(i, labels, depths_mm, K, world_to_cam, points, point_views, rel_tol)
        closed = scipy.ndimage.binary_closing(proj, iterations=closing_px, border_value=0) | proj
        filled = scipy.ndimage.binary_fill_holes(closed)
        # Holes are filled unless depth there says support or background (seen through the object).
        holes = filled & ~closed
        hole_lab, n_holes = scipy.ndimage.label(holes)
        said = np.bincount(hole_lab.ravel(), weights=(own > 0).ravel(), minlength=n_holes + 1)
        said_against = np.bincount(hole_lab.ravel(), weights=against.ravel(), minlength=n_holes + 1)
        open_hole = said_against >= 0.5 * np.maximum(said, 1)  # mostly support or background seen through it
        open_hole[0] = False
        projection = filled & ~open_hole[hole_lab]
        projection = drop_small_components(projection, min_component_fraction)
        inner = scipy.ndimage.binary_erosion(projection, iterations=band_px, border_value=1)
        outer = scipy.ndimage.binary_dilation(projection, iterations=band_px)
        gc = np.full((H, W), GC_PR_BGD, np.uint8)
        gc[projection] = GC_PR_FGD
        gc[inner & ~against] = GC_FGD
        gc[projection & against] = GC_PR_BGD
        # Outside the band the refinement may still take what no evidence decides: pixels
        # whose own depth says nothing and whose ray other views do not look through (a part
        # only this view matched, or none did). Background needs evidence.
        evidence_bg = against | ((own == labelling.UNKNOWN) & refuted_rays(i, labels.region, depths_mm, K, world_to_cam,
                                                                           rel_tol))
        gc[~outer & evidence_bg] = GC_BGD
        gc[~outer & ~silhouette(labels.region, K[i], world_to_cam[i], (H, W), parts="no_footprint")] = GC_BGD
        method = "projection"
        if not projection.any():
            mask = projection
        elif saliency is not None:
            sal = saliency(images[i]) >= 0.5
            mask = (gc == GC_FGD) | (outer & ~(gc == GC_FGD) & sal)
            method = "model"
        else:
            mask = grabcut(images[i], gc, grabcut_iterations, grabcut_max_side, seed)
            if mask is None:
                mask = projection.copy()
            else:
                method = "grabcut"
        refined = mask
        if hole_depth_share > 0:
            mask = fill_depthless_holes(mask, gc, depths_mm[i], hole_depth_share)
        mask = drop_small_components(mask, min_component_fraction)
        facts = {"coverage_projection": round(float(projection.mean()), 4), "coverage_refined": round(float(refined.mean()), 4),
                 "band_px": band_px, "seconds": round(time.perf_counter() - t, 4)}
        results.append(ViewMask(ids[i], mask, float(mask.mean()), method, facts=facts,
                                stages={"projection": projection, "refined": refined, "cleaned": mask.copy()}))
    for i, r in enumerate(results):
        why, check = (("the 3D labelling found no object points", {}) if len(points) == 0 else
                      self_check(r.mask, r.stages["projection"], depths_mm[i], K[i], world_to_cam[i], agreed, rel_tol))
        r.facts.update(check)
        if why is not None:
            fallback = silhouette(labels.region, K[i], world_to_cam[i], (H, W), parts="no_footprint")
            r.warnings.append(f"view {r.view}: {why}; falling back to the region's silhouette (the sphere holding the "
                              f"object, cut by the support plane: {fallback.mean():.1%} of the image)")
            r.mask, r.method = fallback, "fallback_region"
        r.coverage = float(r.mask.mean())
    return results
