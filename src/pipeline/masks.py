"""Object masks derived per input view for captures without masks (issue 58).

No learned weights: the object's bounding region (:mod:`pipeline.meshing.region`: the unit
sphere, the support plane, the object's footprint; :func:`find_region` finds it from the
init's depth maps with the lowest large plane as the table) is applied to the init's depth
maps as a first object / background split, refined in image space by OpenCV's GrabCut
seeded with that split, and made consistent across the views. ``gcgs masks``
(:mod:`pipeline.runs.masks`) writes them into a copy of the prepared scene.

Steps (:func:`derive_masks`):

1. **Seed**, per view (:func:`seed_labels`), GrabCut's four labels:

   * sure background: a pixel whose ray does not cross the sphere above the table
     (:func:`ray_intervals`), or whose depth point lies below the table (+ margin) or
     outside the sphere, unless within ``band_px`` of a foreground depth pixel (mixed
     pixels at silhouettes stay probable background);
   * sure foreground: depth inside the region (footprint included), ``band_px`` away from
     that set's border and, with a table, more than :data:`FG_HEIGHT_MARGINS` plane margins
     above it;
   * probable foreground: the rest of the depth inside the region; depth above the table
     beyond the footprint that runs on without a depth jump from it
     (:func:`depth_components`); pixels without depth in the holes of that set after a
     morphological closing over ``closing_px`` (a textureless part MVS matched at a few
     pixels only: as probable background its pixels would teach GrabCut's background colour
     model the object's colours, and GrabCut then cuts the part out);
   * probable background: every other pixel (no depth; depth above the table beyond the
     footprint and cut off from the object by a depth jump). Without a table, in-sphere
     depth not connected to the piece the cameras aim at (:func:`aim_point`) is probable
     background too.

2. **GrabCut**, per view (``cv2.grabCut``, ``GC_INIT_WITH_MASK``, ``grabcut_iterations``) on
   the image brightness-normalised to 8 bits and downscaled so that its longer side is at
   most ``grabcut_max_side`` (the labels by nearest neighbour); its answer is upscaled
   bilinearly and the sure labels of the full-size seed are put back.

3. **Consistency** across the views: the geometric part is in the seed (a pixel whose ray
   misses the sphere above the table, or whose depth lands on or below the table, is sure
   background in every view, which GrabCut keeps). Then a visual-hull test
   (:func:`cross_view_check`): a foreground pixel of view ``i`` is dropped when its depth
   point (or, without depth, every point of its ray inside the region) projects outside the
   foreground (dilated by ``hull_tolerance_px``) of every other view whose image it lands
   in. Enclosed holes without sure background and (nearly) without depth the seed calls
   background are filled (:func:`fill_depthless_holes`); components smaller than
   ``min_component_fraction`` of the largest are dropped.

4. **Sanity**, per view: a mask covering less than ``min_coverage`` or more than
   ``max_coverage`` of its view is replaced by the silhouette of the region's sphere alone
   (the fallback), with one warning naming the view.

Deterministic: OpenCV's RNG is seeded (``cv2.setRNGSeed``) before every GrabCut call, the
RANSAC of :func:`find_region` is seeded, and the views' results do not depend on their order
beyond the order of the output.

Frames and units (:mod:`pipeline.geometry`): world frame in mm; ``world_to_cam`` is a 4x4
rigid world mm -> OpenCV camera transform; ``K`` is 3x3 for the image's own size with pixel
centres at integer coordinates; depth maps are camera-frame z in mm with 0 = no depth
(:class:`pipeline.init.io.DepthMap`'s ``depth_mm``, never NaN); images are ``(H, W, 3)``
float RGB in [0, 1]; masks are ``(H, W)`` bool, True on the object. Pixel counts
(``band_px``, ``hull_tolerance_px``) are at the images' full size. A ray's parameter ``t``
is its camera depth (directions have camera-frame z = 1).

Settings are keyword arguments with documented defaults until a config section holds them
(the config classes are being reworked; see :func:`derive_masks`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.ndimage

from pipeline import geometry
from pipeline.meshing import region as bounding
from pipeline.meshing.region import Region

GC_BGD, GC_FGD, GC_PR_BGD, GC_PR_FGD = cv2.GC_BGD, cv2.GC_FGD, cv2.GC_PR_BGD, cv2.GC_PR_FGD
# Sure foreground only this many plane margins above the table (the base, where depth noise
# meets the table, stays probable).
FG_HEIGHT_MARGINS = 3.0
# Brightness normalisation before 8-bit quantisation: this percentile of the image maps to 1
# (a dark capture keeps its contrast for GrabCut's colour models).
BRIGHTNESS_PERCENTILE = 99.0
# A plane is a table only when the cameras see its normal pointing up: the median over the
# cameras of its component along their image-up axis (-y) is at least this (DTU: ~0.85).
MIN_UPRIGHT = 0.3
# Planes are peeled off the depth points while they carry this times plane_share of them.
PEEL_SHARE_FACTOR = 1.0 / 3.0
# A table has at most this share of the depth points (in the sphere) below it ...
MAX_BELOW = 0.1
# ... and the cameras' aim (the object) at least this many sphere radii above it.
MIN_AIM_HEIGHT = 0.05
# Without a table, the foreground is the depth-continuous piece nearest to the cameras' aim
# among those of at least this many pixels and this share of the view.
AIM_PIECE_MIN_PX = 20
AIM_PIECE_MIN_SHARE = 0.001
# Points sampled along a ray's stretch inside the region for the visual-hull test.
HULL_RAY_SAMPLES = 48
# A view refutes a point when it sees a surface this much (relative) beyond it.
FREE_SPACE_REL = 0.01
# The cross-view test drops a pixel when at least half of the foreground in this window
# (pixels, square) around it fails the test too.
HULL_VOTE_WINDOW = 5
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
    method: str  # "grabcut" | "seed" (GrabCut skipped: one label class empty) | "fallback_sphere"
    warnings: list[str] = field(default_factory=list)
    facts: dict = field(default_factory=dict)  # pixel counts, coverages per step, seconds
    stages: dict = field(default_factory=dict)  # (H, W) bool masks after each step: seed, grabcut, consistent


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


# ---------------------------------------------------------------------------------------
# The region from the depth maps: the lowest large plane


def hidden_table_points(plane: np.ndarray, sphere: Region, depths_mm: np.ndarray, K: np.ndarray,
                        world_to_cam: np.ndarray, step_mm: float, tol_mm: float) -> np.ndarray:
    """``(M, 3)`` world points (mm) of the table (``plane``, inside ``sphere``), on a grid of
    ``step_mm``, that no view sees as table while some view sees something above the table
    (in the sphere) in front of them: where the object's hidden base may be. A view sees a
    table point when its depth there is within ``max(tol_mm, 1% of it)`` of the point's, and
    something in front of it when its depth is shorter by more than that."""
    n, d0 = plane[:3], float(plane[3])
    dist = float(sphere.centre_mm @ n + d0)
    rad2 = sphere.radius_mm ** 2 - dist ** 2
    if rad2 <= 0:
        return np.zeros((0, 3))
    axes = bounding.plane_axes(n)
    c0 = sphere.centre_mm - dist * n
    g = np.arange(-np.sqrt(rad2), np.sqrt(rad2) + step_mm, step_mm)
    u, v = np.meshgrid(g, g, indexing="ij")
    grid = (c0 + u[..., None] * axes[0] + v[..., None] * axes[1]).reshape(-1, 3)
    seen = np.zeros(len(grid), bool)
    blocked = np.zeros(len(grid), bool)
    above_table = Region(sphere.centre_mm, sphere.radius_mm, plane, 0.0)
    for depth, Ki, T in zip(depths_mm, K, world_to_cam):
        H, W = depth.shape
        px, z = geometry.project(Ki, T, grid)
        with np.errstate(invalid="ignore"):
            ij = np.rint(px)
        ok = (z > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
        d = np.zeros(len(z))
        d[ok] = depth[ij[ok, 1].astype(int), ij[ok, 0].astype(int)]
        tol = np.maximum(tol_mm, 0.01 * z)
        seen |= (d > 0) & (np.abs(d - z) < tol)
        front = np.flatnonzero((d > 0) & (d < z - tol))
        if len(front):
            cam = geometry.pixel_rays(Ki, ij[front, 0], ij[front, 1]) * d[front, None]
            world = (cam - T[:3, 3]) @ T[:3, :3]
            blocked[front[above_table.contains(world)]] = True
    return grid[(u.ravel() ** 2 + v.ravel() ** 2 <= rad2) & blocked & ~seen]


def find_region(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, norm_to_world: np.ndarray,
                voxel_mm: float, plane_share: float, plane_margin_mm: float,
                max_planes: int = 4, hidden_base: bool = True) -> tuple[Region, dict]:
    """The bounding region of :func:`pipeline.meshing.region.region_for_depths` (the unit
    sphere ``norm_to_world``, the half-space ``plane_margin_mm`` above the support plane, the
    footprint), except for which plane is the table (docs: captures without masks, class 1:
    the mesh stage takes the largest plane, which for an object on a block on a table is the
    block's top, and rejects it as most other points lie below it).

    Up to ``max_planes`` planes are peeled off the depth points inside the sphere (seeded
    RANSAC, inliers within 2 voxels, refitted), as long as each carries at least
    ``plane_share`` x :data:`PEEL_SHARE_FACTOR` of them. A plane can be the table when every
    camera is above it, at most :data:`MAX_BELOW` of the points lie below it, the cameras'
    aim (:func:`aim_point`, the object) is at least :data:`MIN_AIM_HEIGHT` sphere radii above
    it, and the cameras see its normal pointing up (the median over the cameras of its
    component along image-up, ``-y``, is at least :data:`MIN_UPRIGHT`: a wall facing the
    cameras is no table). Of those, the table is the **lowest**: the fewest points below it
    (ties within 2% of the points: the larger share).

    The footprint is :func:`pipeline.meshing.region.footprint_hull`'s; with ``hidden_base``
    its points also include the table that no view sees behind the object
    (:func:`hidden_table_points`): views from one side see the near half of the base only,
    and a footprint of that half cuts the far half of the object (the back of a block, the
    top of a ball). Returns the region and facts."""
    sphere = Region(centre_mm=np.asarray(norm_to_world, np.float64)[:3, 3].copy(), radius_mm=float(norm_to_world[0, 0]))
    pts = bounding.depth_points_mm(depths_mm, K, world_to_cam)
    pts = pts[sphere.contains(pts)]
    if len(pts) > bounding.PLANE_SAMPLE:
        pts = pts[np.random.default_rng(0).choice(len(pts), bounding.PLANE_SAMPLE, replace=False)]
    facts: dict = {"planes": []}
    if len(pts) < 3:
        return sphere, facts
    centres = np.stack([geometry.camera_center(T) for T in world_to_cam])
    aim = aim_point(world_to_cam) if len(world_to_cam) >= 2 else sphere.centre_mm
    inlier_mm = 2.0 * voxel_mm
    rest = np.ones(len(pts), bool)
    candidates = []
    for k in range(max_planes):
        if rest.sum() < 3:
            break
        plane, inl = bounding.fit_plane_ransac(pts[rest], inlier_mm, seed=k)
        share = float(inl.sum()) / len(pts)
        if share < PEEL_SHARE_FACTOR * plane_share:
            break
        side = centres @ plane[:3] + plane[3]
        if np.all(side < 0):
            plane, side = -plane, -side
        h = pts @ plane[:3] + plane[3]
        below = float((h < -inlier_mm).mean())
        # Upright cameras see a table's normal pointing up in their images (-y), a wall behind
        # the object facing them pointing down or sideways.
        upright = float(np.median(-world_to_cam[:, 1, :3] @ plane[:3]))
        aim_height = float(aim @ plane[:3] + plane[3]) / sphere.radius_mm
        ok = (bool(np.all(side > 0)) and below <= MAX_BELOW and upright >= MIN_UPRIGHT
              and aim_height >= MIN_AIM_HEIGHT)
        facts["planes"].append({"share": round(share, 4), "below": round(below, 4), "cameras_above": bool(np.all(side > 0)),
                                "upright": round(upright, 3), "aim_height_norm": round(aim_height, 4), "candidate": ok})
        if ok:
            candidates.append((below, -share, k, plane))
        idx = np.flatnonzero(rest)
        rest[idx[inl]] = False
    if not candidates:
        return sphere, facts
    lowest = min(c[0] for c in candidates)
    below, _, k, plane = min(c for c in candidates if c[0] <= lowest + 0.02)
    facts["table_plane"] = k
    pixel_mm = float(np.median([np.linalg.norm(c - sphere.centre_mm) / Ki[0, 0] for c, Ki in zip(centres, K)]))
    cluster_mm = 3.0 * max(voxel_mm, pixel_mm)
    base = pts
    if hidden_base:
        hidden = hidden_table_points(plane, sphere, depths_mm, K, world_to_cam, cluster_mm / 2.0, inlier_mm)
        facts["hidden_table_points"] = len(hidden)
        # Lifted into the band the footprint is taken from (FOOTPRINT_BAND plane margins up).
        lift = 0.5 * (bounding.FOOTPRINT_BAND[0] + bounding.FOOTPRINT_BAND[1]) * plane_margin_mm
        base = np.concatenate([pts, hidden + lift * plane[:3]])
    hull, axes, hull_facts = bounding.footprint_hull(base, plane, plane_margin_mm, cluster_mm)
    region = Region(sphere.centre_mm, sphere.radius_mm, plane, plane_margin_mm, hull, axes,
                    bounding.FOOTPRINT_MARGIN * sphere.radius_mm if hull is not None else 0.0)
    return region, {**facts, **hull_facts}


# ---------------------------------------------------------------------------------------
# Steps


def depth_components(depth_mm: np.ndarray, allowed: np.ndarray, K: np.ndarray, continuity_px: float) -> np.ndarray:
    """``(H, W)`` int labels of the connected components of the ``allowed`` pixels (with
    depth), two 4-neighbours being connected when their depths differ by less than
    ``continuity_px`` pixel footprints (``depth / fx``): a smooth surface, even a slanted one,
    stays one piece; a jump from the object to what lies behind it does not. Pixels not
    ``allowed`` are each their own component."""
    import scipy.sparse
    import scipy.sparse.csgraph

    H, W = depth_mm.shape
    idx = np.arange(H * W).reshape(H, W)
    tol = continuity_px * depth_mm / float(K[0, 0])
    rows, cols = [], []
    for a, b in (((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                 ((slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        ok = allowed[a] & allowed[b] & (np.abs(depth_mm[a] - depth_mm[b]) < np.minimum(tol[a], tol[b]))
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = scipy.sparse.coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(H * W, H * W))
    return scipy.sparse.csgraph.connected_components(graph, directed=False)[1].reshape(H, W)


def aim_point(world_to_cam: np.ndarray) -> np.ndarray:
    """The world point (mm) nearest to every camera's optical axis (least squares): what the
    cameras look at."""
    z = np.asarray(world_to_cam, np.float64)[:, 2, :3]
    centres = np.stack([geometry.camera_center(T) for T in world_to_cam])
    proj = np.eye(3)[None] - z[:, :, None] * z[:, None, :]
    return np.linalg.lstsq(proj.sum(axis=0), np.einsum("nij,nj->i", proj, centres), rcond=None)[0]


def seed_labels(depth_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, region: Region,
                band_px: int, continuity_px: float, aim_mm: np.ndarray | None = None,
                closing_px: int = 0) -> tuple[np.ndarray, dict]:
    """GrabCut's ``(H, W)`` uint8 labels from the region applied to one depth map (module
    docstring, step 1), and pixel counts.

    The footprint is a soft bound: it is the hull of the base the views see, and with views
    from one side it misses the object's far half (the top of a ball, the back of a block).
    Depth above the table and in the sphere but beyond the footprint is probable foreground
    when it runs on without a depth jump (:func:`depth_components`) from the depth inside
    the region, probable background otherwise; only depth below the table or outside the
    sphere is sure background. Without a table (``region.plane`` None) and with ``aim_mm``
    (:func:`aim_point`), only the depth-continuous piece of the in-region depth nearest, in
    the image, to where the aim point projects is foreground (among the pieces of at least
    :data:`AIM_PIECE_MIN_PX` pixels and :data:`AIM_PIECE_MIN_SHARE` of the view: a wrong
    match near the aim is a speck); the rest of the in-region depth (clutter in the sphere)
    is probable background. Pixels without depth (whose ray crosses the region) in the holes
    of the foreground closed over ``closing_px`` pixels are probable foreground (0: in its
    enclosed holes only)."""
    shape = depth_mm.shape
    origin, dirs = pixel_ray_dirs(K, world_to_cam, shape)
    t0, t1 = ray_intervals(region, origin, dirs, parts="no_footprint")
    crosses = t1 > t0
    has = depth_mm > 0
    pts = origin + dirs * depth_mm[..., None]
    flat = pts.reshape(-1, 3)
    unbounded = Region(region.centre_mm, region.radius_mm, region.plane, region.margin_mm)
    above = has & unbounded.contains(flat).reshape(shape)  # in the sphere, above the table
    inside = above & region.contains(flat).reshape(shape) if region.footprint is not None else above.copy()
    grown = np.zeros(shape, bool)
    if region.footprint is not None and inside.any():
        comp = depth_components(depth_mm, above, K, continuity_px)
        grown = above & ~inside & np.isin(comp, np.unique(comp[inside]))
    elsewhere = above & ~inside & ~grown
    if region.plane is None and aim_mm is not None and inside.any():
        comp = depth_components(depth_mm, inside, K, continuity_px)
        ys, xs = np.nonzero(inside)
        size = np.bincount(comp[ys, xs])[comp[ys, xs]]
        big = size >= max(AIM_PIECE_MIN_PX, AIM_PIECE_MIN_SHARE * depth_mm.size)
        ys, xs = (ys[big], xs[big]) if big.any() else (ys, xs)
        px, _ = geometry.project(K, world_to_cam, np.asarray(aim_mm, np.float64)[None])
        k = int(np.argmin((xs - px[0, 0]) ** 2 + (ys - px[0, 1]) ** 2)) if np.isfinite(px).all() else 0
        elsewhere = inside & (comp != comp[ys[k], xs[k]])
        inside = inside & ~elsewhere
    fg = inside | grown
    outside = has & ~above  # below the table or outside the sphere
    near_fg = scipy.ndimage.binary_dilation(fg, iterations=band_px) if band_px > 0 else fg
    sure_fg = scipy.ndimage.binary_erosion(inside, iterations=band_px, border_value=1) if band_px > 0 else inside.copy()
    if region.plane is not None:
        sure_fg &= pts @ region.plane[:3] + region.plane[3] > FG_HEIGHT_MARGINS * region.margin_mm
    # Pixels without depth among the foreground's are probable foreground (module docstring).
    closed = scipy.ndimage.binary_closing(fg, iterations=closing_px) if closing_px > 0 else fg
    holes = scipy.ndimage.binary_fill_holes(closed) & ~has & crosses
    labels = np.full(shape, GC_PR_BGD, np.uint8)
    labels[fg | holes] = GC_PR_FGD
    labels[sure_fg] = GC_FGD
    labels[outside & ~near_fg] = GC_BGD
    labels[~crosses] = GC_BGD
    facts = {"region_silhouette": round(float(crosses.mean()), 4), "depth_pixels": int(has.sum()),
             "depth_inside": int(inside.sum()), "depth_beyond_footprint_kept": int(grown.sum()),
             "depth_above_table_dropped": int(elsewhere.sum()), "depth_outside": int(outside.sum()),
             "hole_pixels": int(holes.sum()), "sure_fg": int((labels == GC_FGD).sum()),
             "sure_bg": int((labels == GC_BGD).sum())}
    return labels, facts


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


def cross_view_check(masks: list[np.ndarray], labels: list[np.ndarray], depths_mm: np.ndarray, K: np.ndarray,
                     world_to_cam: np.ndarray, region: Region, tolerance_px: int,
                     test: str = "free_space") -> list[np.ndarray]:
    """The cross-view test of step 3 (module docstring) on every view against the others as
    given (the order of the views does not matter). A foreground pixel of view ``i`` fails
    when its depth point (without depth: every sample of its ray inside the sphere above the
    table) is refuted by every other view whose image it lands in; it is dropped when at
    least half of the foreground in the :data:`HULL_VOTE_WINDOW` square around it fails too
    (a lone failing pixel is a wrong depth, not background). View ``j`` refutes a point
    landing on its pixel ``q``:

    * ``test="free_space"``: when ``q`` is sure background in ``j``'s seed ``labels`` (shrunk
      by ``tolerance_px``: its ray misses the region, its depth is on or below the table or
      outside the sphere), or when ``j`` sees a surface beyond the point there (the nearest
      depth within ``tolerance_px`` of ``q`` farther than the point's depth in ``j`` by more
      than :data:`FREE_SPACE_REL`): ``j`` looks through where the point would be. A mistake
      in ``j``'s mask refutes nothing.
    * ``test="silhouette"``: when ``q`` is outside ``j``'s mask dilated by ``tolerance_px``
      (the visual hull; a part missing from two views' masks goes from the third too).

    Returns the new masks."""
    if test not in ("free_space", "silhouette"):
        raise ValueError(f"cross_view_check: test must be free_space or silhouette, got {test!r}")
    n = len(masks)
    if n < 2:
        return [m.copy() for m in masks]
    size = 2 * tolerance_px + 1
    if test == "silhouette":
        refuting = [~scipy.ndimage.binary_dilation(m, iterations=tolerance_px) if tolerance_px > 0 else ~m for m in masks]
        nearest = [None] * n
    else:
        refuting = [scipy.ndimage.binary_erosion(lab == GC_BGD, iterations=tolerance_px, border_value=1)
                    if tolerance_px > 0 else lab == GC_BGD for lab in labels]
        nearest = [scipy.ndimage.minimum_filter(np.where(d > 0, d, np.inf), size=size) for d in depths_mm]

    def refuted(points: np.ndarray, j: int) -> np.ndarray:
        """Whether view ``j`` refutes each of the ``(..., 3)`` points (False where it does
        not land in ``j``'s image)."""
        H, W = masks[j].shape
        px, z = geometry.project(K[j], world_to_cam[j], points.reshape(-1, 3))
        with np.errstate(invalid="ignore"):
            ij = np.rint(px)
        lands = (z > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
        rows, cols = ij[lands, 1].astype(int), ij[lands, 0].astype(int)
        out = np.zeros(len(z), bool)
        no = refuting[j][rows, cols]
        if nearest[j] is not None:
            near = nearest[j][rows, cols]  # inf: no depth around q, no evidence
            no |= np.isfinite(near) & (near > z[lands] * (1.0 + FREE_SPACE_REL))
        out[lands] = no
        return out.reshape(points.shape[:-1])

    out = []
    for i in range(n):
        keep = masks[i].copy()
        fails = np.zeros(keep.shape, bool)
        ys, xs = np.nonzero(masks[i])
        if len(ys) == 0:
            out.append(keep)
            continue
        origin, dirs = pixel_ray_dirs(K[i], world_to_cam[i], masks[i].shape)
        d = depths_mm[i][ys, xs]
        rays = dirs[ys, xs]
        has = d > 0
        t0, t1 = ray_intervals(region, origin, rays[~has], parts="no_footprint")
        frac = (np.arange(HULL_RAY_SAMPLES) + 0.5) / HULL_RAY_SAMPLES
        for which, ts in ((has, d[has, None]), (~has, t0[:, None] + (np.maximum(t1, t0) - t0)[:, None] * frac)):
            pts = origin + rays[which][:, None, :] * ts[..., None]  # (P, S, 3)
            agree = np.ones(ts.shape, bool)  # refuted by no other view
            for j in range(n):
                if j != i:
                    agree &= ~refuted(pts, j)
            fails[ys[which], xs[which]] = ~agree.any(axis=1)
        share = scipy.ndimage.uniform_filter(fails.astype(np.float64), HULL_VOTE_WINDOW, mode="constant")
        around = scipy.ndimage.uniform_filter(masks[i].astype(np.float64), HULL_VOTE_WINDOW, mode="constant")
        keep &= ~(fails & (share >= 0.5 * around))
        out.append(keep)
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


def derive_masks(images: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, depths_mm: np.ndarray,
                 region: Region, view_ids: list[int] | None = None, *, band_px: int = 2, continuity_px: float = 8.0,
                 grabcut_iterations: int = 4, grabcut_max_side: int = 400, hull_tolerance_px: int = 2,
                 min_component_fraction: float = 0.01, consistency: bool = True, hull_test: str = "free_space",
                 hole_depth_share: float = 0.1, hole_closing_share: float = 0.01,
                 min_coverage: float = 0.01,
                 max_coverage: float = 0.9, seed: int = 0) -> list[ViewMask]:
    """Object masks of the input views of a capture without masks (module docstring).

    ``images``: ``(N, H, W, 3)`` float RGB in [0, 1]; ``K`` ``(N, 3, 3)`` at ``(H, W)``;
    ``world_to_cam`` ``(N, 4, 4)`` world mm; ``depths_mm`` ``(N, H, W)`` camera z in mm, 0 =
    no depth (the init's depth maps); ``region``: the object's bounding region (world mm;
    :func:`find_region` or :func:`pipeline.meshing.region.region_for_depths`); ``view_ids``
    name the views in facts and warnings (default 0..N-1).

    Settings (keyword arguments until a config section holds them): ``band_px`` (2): pixels
    at the border of the in-region depth that stay probable, not sure, labels;
    ``continuity_px`` (8): neighbouring depths closer than this many pixel footprints are
    one surface (:func:`depth_components`);
    ``grabcut_iterations`` (4) and ``grabcut_max_side`` (400 px: GrabCut runs on the image
    downscaled to this longer side); ``consistency`` (True): run the cross-view test of step
    3 (:func:`cross_view_check`), ``hull_test`` (``free_space``) the kind,
    ``hull_tolerance_px`` (2) its tolerance in pixels; ``min_component_fraction`` (0.01):
    smaller components of a mask are dropped; ``hole_depth_share`` (0.1): enclosed holes of a
    mask with no sure background seed and at most this share of pixels with background depth
    are filled (:func:`fill_depthless_holes`; 0: off); ``hole_closing_share`` (0.01): pixels
    without depth in the holes of the foreground seed closed over this share of the image's
    longer side are probable foreground (0: only its enclosed holes);
    ``min_coverage`` / ``max_coverage`` (0.01 / 0.9): outside these the view falls back to
    the sphere's silhouette with a warning (the other views' cross-view test has already
    run with its derived mask: harmless for ``free_space``, which reads the other views'
    seeds and depth, not their masks); ``seed`` (0): OpenCV's RNG seed.

    Returns one :class:`ViewMask` per view, in order."""
    images = np.asarray(images)
    depths_mm = np.asarray(depths_mm, np.float64)
    n, H, W = depths_mm.shape
    if images.shape[:3] != (n, H, W) or len(K) != n or len(world_to_cam) != n:
        raise ValueError(f"derive_masks: images {images.shape}, K {np.shape(K)}, world_to_cam {np.shape(world_to_cam)} "
                         f"and depths {depths_mm.shape} must describe the same N views of one size")
    if not np.all(np.isfinite(depths_mm)) or np.any(depths_mm < 0):
        raise ValueError("derive_masks: depth must be finite and >= 0 (0 = no depth)")
    ids = list(range(n)) if view_ids is None else [int(v) for v in view_ids]
    aim = aim_point(world_to_cam) if n >= 2 else None
    closing_px = round(hole_closing_share * max(H, W))
    results, seeds_fg, cut, all_labels = [], [], [], []
    for i in range(n):
        t = time.perf_counter()
        labels, facts = seed_labels(depths_mm[i], K[i], world_to_cam[i], region, band_px, continuity_px, aim,
                                    closing_px)
        seed_fg = (labels == GC_FGD) | (labels == GC_PR_FGD)
        mask, method = grabcut(images[i], labels, grabcut_iterations, grabcut_max_side, seed), "grabcut"
        if mask is None:
            mask, method = seed_fg.copy(), "seed"
        facts["seconds_seed_grabcut"] = round(time.perf_counter() - t, 4)
        results.append(ViewMask(ids[i], mask, float(mask.mean()), method, facts=facts,
                                stages={"seed": seed_fg, "grabcut": mask}))
        seeds_fg.append(seed_fg)
        all_labels.append(labels)
        cut.append(mask)
    t = time.perf_counter()
    if consistency:
        cut = cross_view_check(cut, all_labels, depths_mm, K, world_to_cam, region, hull_tolerance_px, hull_test)
    if hole_depth_share > 0:
        cut = [fill_depthless_holes(m, lab, d, hole_depth_share) for m, lab, d in zip(cut, all_labels, depths_mm)]
    cut = [drop_small_components(m, min_component_fraction) for m in cut]
    per_view = (time.perf_counter() - t) / n
    for i, r in enumerate(results):
        r.stages["consistent"] = cut[i]
        r.facts["seconds_consistency"] = round(per_view, 4)
        r.facts.update(coverage_seed=round(float(seeds_fg[i].mean()), 4), coverage_grabcut=round(float(r.mask.mean()), 4),
                       coverage_consistent=round(float(cut[i].mean()), 4))
        r.mask, r.coverage = cut[i], float(cut[i].mean())
        if not min_coverage <= r.coverage <= max_coverage:
            sphere = silhouette(region, K[i], world_to_cam[i], (H, W), parts="sphere")
            r.warnings.append(f"view {r.view}: the derived mask covers {r.coverage:.1%} of the image (outside "
                              f"[{min_coverage:.0%}, {max_coverage:.0%}]); falling back to the region's sphere alone "
                              f"(its silhouette covers {sphere.mean():.1%})")
            r.mask, r.coverage, r.method = sphere, float(sphere.mean()), "fallback_sphere"
    return results
