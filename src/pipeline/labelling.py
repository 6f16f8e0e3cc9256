"""Object, support and background: one decision in 3D for a capture without masks.

``gcgs masks`` and ``gcgs prepare`` project this labelling into every input view
(:mod:`pipeline.masks`). The mesh stage's region for depth fused without masks
(:mod:`pipeline.meshing.region`, whose :class:`~pipeline.meshing.region.Region` and plane fit
this module uses) does not read it yet: that move, which reruns the whole DVC pipeline, is
issue 77's open part (docs/inputs.md).

:func:`label_scene` labels the depth points of every view at once:

1. **Noise, measured.** The depth maps' relative noise ``noise_rel`` is the robust spread
   (1.4826 x MAD) of the relative depth differences where one view's points land on another
   view's depth (:func:`cross_view_noise`). Every tolerance below is a multiple of a measured
   spread, floored by the scene's own resolution (one voxel), never a fixed share.
2. **The support.** Planes are peeled off the points in the search sphere (the unit sphere
   grown by :data:`SEARCH_GROWTH`): seeded RANSAC, then refitted while the inlier band is
   re-derived from the residuals' own spread (:func:`refine_plane`: ``sigma`` = 1.4826 x MAD,
   band ``NOISE_K`` x sigma). A plane can carry the object when every camera is above it,
   it is level (its normal within :data:`MAX_TILT_DEG` of :func:`up_direction`), the cameras' aim is above
   it, and more points stand on it than lie below it. Of those the support is the
   **lowest** (the one the aim stands highest above): a block on a table has its top as the
   largest plane and the table as the lowest.
3. **The object**: points above the support (by its band) inside the search sphere that no
   other view sees through (free-space carving, :func:`seen_through`), grouped by 3D
   connectivity (:func:`connected_pieces`): with a support, the pieces that stand on it
   (:func:`supported_pieces`) and that every view looking at them confirms
   (:func:`confirmed_pieces`); without one (an object on a stand before clutter), the
   pieces the cameras aim at (:func:`aimed_pieces`).
4. **The region**: the sphere grown to hold every object point (never cutting the object,
   at most the search sphere), the half-space above the support, and the object's
   footprint on the support pushed out by :data:`FOOTPRINT_MARGIN` radii (overhangs).

Frames and units (:mod:`pipeline.geometry`): world frame in mm (a capture's own units);
``world_to_cam`` 4x4 world -> OpenCV camera; ``K`` for the depth maps' size, pixel centres at
integer coordinates; depth is camera z in mm, 0 = none. A plane is ``(n, d)`` with ``|n| = 1``
and ``n . x + d > 0`` above it (the cameras' side).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage

from pipeline import geometry
from pipeline.meshing.region import Region, fit_plane_ransac, plane_axes

# Spreads: sigma = MAD_TO_SIGMA x median absolute deviation (a normal's).
MAD_TO_SIGMA = 1.4826
# A point is on a plane within NOISE_K sigma of its residual spread; above or below beyond it.
NOISE_K = 4.0
# The search for the object and the support looks this far beyond the unit sphere (x radius).
SEARCH_GROWTH = 1.5
# The region's sphere holds every object point plus this share of the unit radius.
SPHERE_MARGIN = 0.05
# Planes are peeled while one carries at least this share of the points in the search sphere.
PLANE_MIN_SHARE = 0.05
MAX_PLANES = 4
PLANE_SAMPLE = 100_000  # points the RANSAC looks at (seeded subsample)
# A support is level: its normal within this angle of the cameras' up (:func:`up_direction`;
# a roof or a wall is no support).
MAX_TILT_DEG = 30.0
# Points are linked into pieces within this share of the unit radius (coarse voxels, 26-neighbours).
LINK_SHARE = 0.02
# Pieces smaller than this share of the largest piece are specks (wrong matches).
MIN_PIECE_SHARE = 0.01
# Without a support: the main piece has the most points within this share of the radius of the aim.
AIM_RADIUS_SHARE = 0.25
# A piece touches the support when its lowest points are within this share of the radius above it.
TOUCH_SHARE = 0.1
# A view that sees most of a piece confirms at least this share of it (its own points or agreeing depth).
MIN_CONFIRMED = 0.1
# The footprint's edges pushed out by this many unit radii.
FOOTPRINT_MARGIN = 0.2
# Free-space carving: a view refutes a point when the nearest depth in this window around its
# pixel lies beyond the point by more than the tolerance.
CARVE_WINDOW = 5
# The relative tolerance of a depth comparison is NOISE_K x the measured relative noise,
# at least this (the depth maps' pixel-level discretisation on slanted surfaces).
MIN_REL_TOL = 0.005
# Relative depth differences beyond this are other surfaces, not noise, when measuring noise.
NOISE_WINDOW_REL = 0.05

# Labels of depth pixels; UNKNOWN: no depth, or a match another view looks through.
UNKNOWN, OBJECT, SUPPORT, BACKGROUND = 0, 1, 2, 3


@dataclass
class SceneLabels:
    """The labelling of every view's depth pixels and the region it implies."""

    region: Region  # where the object may be (meshing and the masks' fallback)
    pixel_labels: np.ndarray  # (N, H, W) uint8: UNKNOWN, OBJECT, SUPPORT, BACKGROUND
    noise_rel: float  # measured relative depth noise (sigma), dimensionless
    support_sigma_mm: float  # measured spread of the support plane's residuals (0 without one)
    facts: dict = field(default_factory=dict)

    @property
    def plane(self) -> np.ndarray | None:
        return self.region.plane

    def object_points(self, depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(points (M, 3) world mm, view (M,))`` of the pixels labelled OBJECT."""
        pts, views = [], []
        for i, (d, Ki, T) in enumerate(zip(depths_mm, K, world_to_cam)):
            sel = self.pixel_labels[i] == OBJECT
            pts.append(geometry.backproject_depth(Ki, T, d)[sel])
            views.append(np.full(int(sel.sum()), i))
        return np.concatenate(pts), np.concatenate(views)


# ---------------------------------------------------------------------------------------
# Planes


def least_squares_plane(points: np.ndarray) -> np.ndarray:
    """``(4,)`` the total-least-squares plane of ``points`` (at least 3)."""
    centroid = points.mean(axis=0)
    n = np.linalg.svd(points - centroid, full_matrices=False)[2][-1]
    return np.append(n, -n @ centroid)


def refine_plane(points: np.ndarray, plane: np.ndarray, floor_mm: float, rounds: int = 30) -> tuple[np.ndarray, float]:
    """The plane refitted to its own inliers while the band is re-derived from their spread:
    ``sigma`` = 1.4826 x MAD of the residuals within the band, band = ``NOISE_K`` x sigma (at
    least ``floor_mm``), until the band settles (a band narrower than the noise truncates the
    residuals and reads a smaller spread: it widens at most twofold a round, so one round
    cannot jump to another surface). Returns ``(plane, sigma_mm)``."""
    band = floor_mm
    sigma = 0.0
    for _ in range(rounds):
        inl = np.abs(points @ plane[:3] + plane[3]) < band
        if inl.sum() < 3:
            break
        plane = least_squares_plane(points[inl])
        r = points[inl] @ plane[:3] + plane[3]
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(r - np.median(r))))
        new_band = float(np.clip(NOISE_K * sigma, floor_mm, 2.0 * band))
        if abs(new_band - band) <= 1e-3 * band:
            break
        band = new_band
    return plane, sigma


# ---------------------------------------------------------------------------------------
# Views


def aim_point(world_to_cam: np.ndarray) -> np.ndarray:
    """The world point (mm) nearest to every camera's optical axis (least squares): what the
    cameras look at."""
    z = np.asarray(world_to_cam, np.float64)[:, 2, :3]
    centres = np.stack([geometry.camera_center(T) for T in world_to_cam])
    proj = np.eye(3)[None] - z[:, :, None] * z[:, None, :]
    return np.linalg.lstsq(proj.sum(axis=0), np.einsum("nij,nj->i", proj, centres), rcond=None)[0]


def up_direction(world_to_cam: np.ndarray) -> np.ndarray:
    """The world's up (unit, world frame) as the cameras show it: cameras are held without
    roll, so every image's x axis is level and up is the direction most orthogonal to all of
    them (the smallest eigenvector of their scatter), signed towards the images' up (-y).
    Where the x axes leave it undetermined (all parallel: cameras on a line with one
    orientation), the images' mean up made orthogonal to their mean x axis."""
    T = np.asarray(world_to_cam, np.float64)
    x, y_up = T[:, 0, :3], -T[:, 1, :3]
    w, v = np.linalg.eigh(x.T @ x)
    u = v[:, 0]
    if w[1] < 1e-3 * len(T):
        mx = x.mean(axis=0) / np.linalg.norm(x.mean(axis=0))
        u = y_up.mean(axis=0) - (y_up.mean(axis=0) @ mx) * mx
        u /= np.linalg.norm(u)
    return u if float((y_up @ u).sum()) >= 0 else -u


def pixel_of(K: np.ndarray, world_to_cam: np.ndarray, points: np.ndarray,
             shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(rows, cols, z, lands)``: the nearest pixel centre of each point, its camera depth,
    and whether it lands in front of the camera inside the image (rows/cols 0 where not)."""
    H, W = shape
    px, z = geometry.project(K, world_to_cam, points)
    with np.errstate(invalid="ignore"):
        ij = np.rint(px)
        lands = (z > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
    rows = np.where(lands, ij[:, 1], 0).astype(np.int64)
    cols = np.where(lands, ij[:, 0], 0).astype(np.int64)
    return rows, cols, z, lands


def sample_depth(depth_mm: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Bilinear depth at ``(M, 2)`` pixel positions (x, y; pixel centres at integers), 0
    where any of the four neighbours is outside the image or has no depth, or where they
    span more than :data:`NOISE_WINDOW_REL` (an edge between surfaces)."""
    H, W = depth_mm.shape
    out = np.zeros(len(px))
    with np.errstate(invalid="ignore"):
        x0, y0 = np.floor(px[:, 0]), np.floor(px[:, 1])
        ok = np.isfinite(px).all(axis=1) & (x0 >= 0) & (y0 >= 0) & (x0 < W - 1) & (y0 < H - 1)
    x0, y0 = x0[ok].astype(np.int64), y0[ok].astype(np.int64)
    fx, fy = px[ok, 0] - x0, px[ok, 1] - y0
    q = np.stack([depth_mm[y0, x0], depth_mm[y0, x0 + 1], depth_mm[y0 + 1, x0], depth_mm[y0 + 1, x0 + 1]])
    good = (q > 0).all(axis=0) & (q.max(axis=0) <= q.min(axis=0) * (1.0 + NOISE_WINDOW_REL))
    val = (q[0] * (1 - fx) + q[1] * fx) * (1 - fy) + (q[2] * (1 - fx) + q[3] * fx) * fy
    out[np.flatnonzero(ok)] = np.where(good, val, 0.0)
    return out


def cross_view_noise(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, sample: int = 20_000,
                     seed: int = 0) -> float:
    """The depth maps' relative noise (sigma of a difference of two views' depths,
    dimensionless): where a view's depth point lands on another view's depth (bilinear,
    :func:`sample_depth`), ``(d_j - z_j) / z_j``; its robust spread over the pairs whose
    difference is within :data:`NOISE_WINDOW_REL` (larger ones are other surfaces). 0 with
    fewer than two views or no overlap."""
    rng = np.random.default_rng(seed)
    diffs = []
    n = len(depths_mm)
    for i in range(n):
        ys, xs = np.nonzero(depths_mm[i] > 0)
        if len(ys) == 0:
            continue
        pick = rng.choice(len(ys), min(sample, len(ys)), replace=False)
        ys, xs = ys[pick], xs[pick]
        cam = geometry.pixel_rays(K[i], xs.astype(np.float64), ys.astype(np.float64)) * depths_mm[i][ys, xs, None]
        T = np.asarray(world_to_cam[i], np.float64)
        world = (cam - T[:3, 3]) @ T[:3, :3]
        for j in range(n):
            if j == i:
                continue
            px, z = geometry.project(K[j], world_to_cam[j], world)
            dj = sample_depth(depths_mm[j], px)
            ok = (dj > 0) & (z > 0)
            rel = (dj[ok] - z[ok]) / z[ok]
            diffs.append(rel[np.abs(rel) < NOISE_WINDOW_REL])
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    if len(d) < 10:
        return 0.0
    return MAD_TO_SIGMA * float(np.median(np.abs(d - np.median(d))))


def seen_through(points: np.ndarray, source_view: np.ndarray, depths_mm: np.ndarray, K: np.ndarray,
                 world_to_cam: np.ndarray, rel_tol: float) -> np.ndarray:
    """``(M,)`` bool: points (from view ``source_view``) that another view looks through:
    the nearest depth in the :data:`CARVE_WINDOW` square around the point's pixel in that view
    lies beyond the point by more than ``rel_tol`` of its depth (free space where the point
    would be)."""
    out = np.zeros(len(points), bool)
    for j in range(len(depths_mm)):
        others = source_view != j
        if not others.any():
            continue
        nearest = scipy.ndimage.minimum_filter(np.where(depths_mm[j] > 0, depths_mm[j], np.inf), size=CARVE_WINDOW)
        rows, cols, z, lands = pixel_of(K[j], world_to_cam[j], points[others], depths_mm[j].shape)
        near = nearest[rows, cols]
        out[np.flatnonzero(others)] |= lands & np.isfinite(near) & (near > z * (1.0 + rel_tol))
    return out


def connected_pieces(points: np.ndarray, link_mm: float) -> np.ndarray:
    """``(M,)`` int piece id of each point: points in 26-neighbouring cubic cells of side
    ``link_mm`` are one piece."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    cell = np.floor((points - points.min(axis=0)) / link_mm).astype(np.int64)
    shape = cell.max(axis=0) + 1
    if np.prod(shape.astype(np.float64)) > 2e8:  # a degenerate spread: fall back to one piece
        return np.zeros(len(points), np.int64)
    occupied = np.zeros(tuple(shape), bool)
    occupied[cell[:, 0], cell[:, 1], cell[:, 2]] = True
    lab, _ = scipy.ndimage.label(occupied, structure=np.ones((3, 3, 3)))
    return lab[cell[:, 0], cell[:, 1], cell[:, 2]] - 1


def confirmed_pieces(points: np.ndarray, source_view: np.ndarray, piece: np.ndarray, sizes: np.ndarray,
                     depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, rel_tol: float) -> np.ndarray:
    """``(P,)`` bool per piece: every view that sees most of the piece (its points land in
    the image and nothing nearer hides them) has depth agreeing with at least
    :data:`MIN_CONFIRMED` of those points, or they are its own. Two views that match a
    repetitive texture at the same wrong depth make a consistent surface that a third view,
    looking at the same place, does not find."""
    ok = np.ones(len(sizes), bool)
    for j in range(len(depths_mm)):
        rows, cols, z, lands = pixel_of(K[j], world_to_cam[j], points, depths_mm[j].shape)
        d = depths_mm[j][rows, cols]
        own = source_view == j
        sees = own | (lands & ~((d > 0) & (d < z * (1.0 - rel_tol))))
        agree = own | (sees & (d > 0) & (np.abs(d - z) <= rel_tol * z))
        n_sees = np.bincount(piece, weights=sees, minlength=len(sizes))
        n_agree = np.bincount(piece, weights=agree, minlength=len(sizes))
        ok &= ~((n_sees >= 0.5 * sizes) & (n_agree < MIN_CONFIRMED * n_sees))
    return ok


def aimed_pieces(aim_dist: np.ndarray, piece: np.ndarray, sizes: np.ndarray, near_mm: float) -> np.ndarray:
    """``(P,)`` bool per piece (those of ``sizes`` 0 left out): what the cameras look at,
    without a support to stand on. The main piece has the most points within ``near_mm`` of the aim (the nearest piece when none
    has any); kept with it are the pieces at least as central, their median distance to the
    aim no larger than its own (an object in several parts). A stand below the object or
    clutter behind it lies farther out than the object it holds or frames."""
    near = np.bincount(piece, weights=aim_dist <= near_mm, minlength=len(sizes)) * (sizes > 0)
    order = np.lexsort((aim_dist, piece))
    starts = np.searchsorted(piece[order], np.arange(len(sizes)))
    median = aim_dist[order][np.minimum(starts + (sizes - 1) // 2, len(order) - 1)]
    main = int(np.argmax(near)) if near.max() > 0 else int(np.argmin(np.where(sizes > 0, median, np.inf)))
    return (sizes > 0) & (median <= median[main])


def supported_pieces(points: np.ndarray, piece: np.ndarray, sizes: np.ndarray, plane: np.ndarray,
                     radius_mm: float) -> np.ndarray:
    """``(P,)`` bool per piece: what stands on the support. A piece touches the support when
    its lowest point is within :data:`TOUCH_SHARE` radii of it (MVS leaves the contact itself
    without depth, and a ball shows little of its underside); a piece above the support stands on the
    object when most of its points lie over the touching pieces' footprint pushed out by
    :data:`FOOTPRINT_MARGIN` radii (a rod's tip whose foot MVS missed). A piece floating
    elsewhere stands on nothing."""
    h = points @ plane[:3] + plane[3]
    low = np.full(len(sizes), np.inf)
    np.minimum.at(low, piece, h)
    touching = low <= TOUCH_SHARE * radius_mm
    if not touching.any():
        return touching
    hull, axes = footprint_hull(points[touching[piece]], plane)
    if hull is None:
        return touching
    xy = points @ axes.T
    inside = (xy @ hull[:, :2].T + hull[:, 2]).max(axis=-1) <= FOOTPRINT_MARGIN * radius_mm
    over = np.bincount(piece, weights=inside, minlength=len(sizes)) >= 0.5 * sizes
    return touching | over


def footprint_hull(points_mm: np.ndarray, plane: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """The object's footprint on the support: the 2D convex hull (``(E, 3)`` half-planes,
    see :class:`Region`) of the object points projected into the plane. ``None`` with fewer
    than 3 points or all on a line."""
    from scipy.spatial import ConvexHull, QhullError

    axes = plane_axes(plane[:3])
    if len(points_mm) < 3:
        return None, axes
    try:
        return ConvexHull(points_mm @ axes.T).equations, axes
    except QhullError:
        return None, axes


# ---------------------------------------------------------------------------------------


def label_scene(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, norm_to_world: np.ndarray,
                voxel_mm: float, min_margin_mm: float = 0.0) -> SceneLabels:
    """Label every depth pixel of the ``(N, H, W)`` depth maps (module docstring).
    ``voxel_mm`` is the scene's resolution (the smallest tolerance); ``min_margin_mm`` the
    least height above the support that is object (the mesh stage's plane margin)."""
    depths_mm = np.asarray(depths_mm, np.float64)
    n, H, W = depths_mm.shape
    S = np.asarray(norm_to_world, np.float64)
    unit = Region(S[:3, 3].copy(), float(S[0, 0]))
    R = unit.radius_mm
    search = Region(unit.centre_mm, SEARCH_GROWTH * R)
    facts: dict = {"planes": []}
    world = np.stack([geometry.backproject_depth(Ki, T, d) for d, Ki, T in zip(depths_mm, K, world_to_cam)])
    has = depths_mm > 0
    labels = np.where(has, BACKGROUND, 0).astype(np.uint8)
    noise_rel = cross_view_noise(depths_mm, K, world_to_cam) if n >= 2 else 0.0
    rel_tol = max(MIN_REL_TOL, NOISE_K * noise_rel)
    facts["noise_rel"] = round(noise_rel, 6)

    in_search = has & search.contains(world)
    pts_all = world[in_search]
    if len(pts_all) < 3:
        facts["object_points"] = 0
        return SceneLabels(unit, labels, noise_rel, 0.0, facts)
    sample = pts_all
    if len(sample) > PLANE_SAMPLE:
        sample = sample[np.random.default_rng(0).choice(len(sample), PLANE_SAMPLE, replace=False)]
    centres = np.stack([geometry.camera_center(T) for T in world_to_cam])
    up = up_direction(world_to_cam)
    aim = aim_point(world_to_cam) if n >= 2 else unit.centre_mm
    if not search.contains(aim[None])[0]:
        aim = unit.centre_mm
    # Planes: the RANSAC's first band is the scene's resolution or the depth noise at the
    # aim, the larger; refine_plane then measures each plane's own spread.
    depth_at_aim = float(np.median(np.linalg.norm(centres - aim, axis=1)))
    floor = max(2.0 * voxel_mm, NOISE_K * noise_rel * depth_at_aim)
    rest = np.ones(len(sample), bool)
    candidates = []
    for k in range(MAX_PLANES):
        if rest.sum() < 3:
            break
        try:
            plane, _ = fit_plane_ransac(sample[rest], floor, seed=k)
        except ValueError:  # what is left lies on a line: no further plane
            break
        plane, sigma = refine_plane(sample[rest], plane, floor)
        band = max(floor, NOISE_K * sigma)
        r_all = sample @ plane[:3] + plane[3]
        on = np.abs(r_all) < band
        share = float((on & rest).sum()) / len(sample)
        if share < PLANE_MIN_SHARE:
            break
        side = centres @ plane[:3] + plane[3]
        if np.all(side < 0):
            plane, side, r_all = -plane, -side, -r_all
        above, below = int((r_all > band).sum()), int((r_all < -band).sum())
        tilt = float(np.degrees(np.arccos(np.clip(plane[:3] @ up, -1.0, 1.0))))
        aim_height = float(aim @ plane[:3] + plane[3])
        ok = bool(np.all(side > 0)) and tilt <= MAX_TILT_DEG and aim_height > band and above >= below
        facts["planes"].append({"share": round(share, 4), "sigma_mm": round(sigma, 4), "band_mm": round(band, 4),
                                "above": round(above / len(sample), 4), "below": round(below / len(sample), 4),
                                "cameras_above": bool(np.all(side > 0)), "tilt_deg": round(tilt, 1),
                                "aim_height_norm": round(aim_height / R, 4), "candidate": ok})
        if ok:
            candidates.append((aim_height, k, plane, sigma, band))
        rest &= ~on

    plane, sigma, margin = None, 0.0, 0.0
    if candidates:
        _, k, plane, sigma, band = max(candidates, key=lambda c: (c[0], -c[1]))
        margin = max(band, min_margin_mm)
        facts["support_plane"] = k

    # The object: above the support, inside the search sphere, not seen through, pieces.
    cand = in_search.copy()
    if plane is not None:
        h = world @ plane[:3] + plane[3]
        labels[has & (np.abs(h) <= margin)] = SUPPORT
        cand &= h > margin
    ids = np.nonzero(cand)
    pts = world[ids]
    views = ids[0]
    through = seen_through(pts, views, depths_mm, K, world_to_cam, rel_tol) if n >= 2 else np.zeros(len(pts), bool)
    facts["seen_through"] = int(through.sum())
    keep = ~through
    piece = connected_pieces(pts[keep], LINK_SHARE * R)
    chosen = np.zeros(keep.sum(), bool)
    if len(piece):
        sizes = np.bincount(piece)
        big = sizes >= MIN_PIECE_SHARE * sizes.max()
        kp = pts[keep]
        chosen_pieces = np.zeros(len(sizes), bool)
        if plane is not None:
            confirmed = confirmed_pieces(kp, views[keep], piece, sizes, depths_mm, K, world_to_cam, rel_tol)
            chosen_pieces = big & supported_pieces(kp, piece, sizes, plane, R) & confirmed
        if not chosen_pieces.any():
            chosen_pieces = aimed_pieces(np.linalg.norm(kp - aim, axis=1), piece, np.where(big, sizes, 0),
                                         AIM_RADIUS_SHARE * R)
        chosen = chosen_pieces[piece]
        facts["pieces"] = int(len(sizes))
        facts["pieces_kept"] = int(len(np.unique(piece[chosen])))
    obj = np.zeros(len(pts), bool)
    obj[np.flatnonzero(keep)[chosen]] = True
    labels[tuple(i[obj] for i in ids)] = OBJECT
    # A point another view looks through is a disputed match, not evidence of background in
    # its own view: it is labelled as if it had no depth.
    labels[tuple(i[through] for i in ids)] = UNKNOWN
    obj_pts = pts[obj]
    facts["object_points"] = int(obj.sum())

    # The region: the sphere grown to hold the object, the support, the footprint.
    radius = R
    if len(obj_pts):
        reach = float(np.linalg.norm(obj_pts - unit.centre_mm, axis=1).max())
        radius = float(np.clip(reach + SPHERE_MARGIN * R, R, SEARCH_GROWTH * R))
    region = Region(unit.centre_mm, radius, plane, margin)
    if plane is not None:
        hull, axes = footprint_hull(obj_pts, plane)
        if hull is not None:
            region = Region(unit.centre_mm, radius, plane, margin, hull, axes, FOOTPRINT_MARGIN * R)
    facts["sphere_growth"] = round(radius / R, 4)
    return SceneLabels(region, labels, noise_rel, sigma, facts)
