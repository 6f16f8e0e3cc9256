"""Preparing a capture for training: the selected views at the training size, with every
camera and mask of the source kept (so held-out views stay usable for mask culling and
checks), all scaled to the new size, written as a DTU-layout scene. The source is a DTU
scan, a COLMAP or a nerfstudio folder (:mod:`pipeline.data.layouts`, docs/inputs.md).
The aspect ratio is never changed.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

from pipeline import geometry
from pipeline.atomic import atomic_dir
from pipeline.config.data import DataConfig
import cv2
import numpy as np

from pipeline.data import dtu, layouts
from pipeline.data.capture import Capture, sphere_matrix
from pipeline.data.scene import Scene, SceneError
from pipeline.errors import print_warning

MIN_VIEWS = 2
MIN_SIDE_PX = 16  # below this no NCC patch or SSIM window fits
MAX_UPSAMPLE = 4.0  # beyond this a typo (--width 100000) rather than a choice


def height_for_width(src: str | Path, width: int, stored: tuple[int, int] | None = None) -> int:
    """Training height that keeps the aspect ratio of ``src``'s images (``stored`` = their
    (width, height) when already read) at ``width``."""
    src_w, src_h = stored or layouts.stored_image_size(src)
    return max(1, round(width * src_h / src_w))


def check_aspect(src: str | Path, stored: tuple[int, int], width: int, height: int) -> None:
    """Refuse a training size whose aspect ratio differs from the source images' (``stored``:
    their width, height) by more than the rounding of the height to whole pixels (resizing
    would squash the image)."""
    src_w, src_h = stored
    if abs(height - width * src_h / src_w) >= 1.0:
        raise SceneError(
            f"{layouts.image_dir(src)}: source images are {src_w}x{src_h} (aspect {src_w / src_h:.3f}) but the "
            f"training size {width}x{height} has aspect {width / height:.3f}; resizing would squash them. "
            f"Give --width alone (the height follows: {height_for_width(src, width, stored)} at width {width}) or "
            "set data.width and data.height in the source's aspect"
        )


def check_size(src: Path, stored: tuple[int, int], width: int, height: int, warn: Callable[[str], None]) -> None:
    """Refuse a training size too small to hold a patch or more than
    :data:`MAX_UPSAMPLE` times the source; warn when it upsamples (no detail is gained)."""
    where = layouts.image_dir(src)
    if min(width, height) < MIN_SIDE_PX:
        raise SceneError(f"data.width/height: training size {width}x{height} is below {MIN_SIDE_PX} px on a side "
                         f"(images of {where} are {stored[0]}x{stored[1]})")
    factor = width / stored[0]
    if factor > MAX_UPSAMPLE:
        raise SceneError(f"data.width/height: training size {width}x{height} upsamples the {stored[0]}x{stored[1]} "
                         f"images of {where} {factor:.1f} times (at most {MAX_UPSAMPLE:g}): choose a smaller size")
    if factor > 1.0:
        warn(f"{where}: training size {width}x{height} upsamples the {stored[0]}x{stored[1]} source images "
             f"{factor:.2f} times; it adds pixels to train on, not detail")


def input_views(src: str | Path, given: list[int] | None, dtu_views: list[int]) -> list[int]:
    """The views to train on: ``given`` (``--views``) if any; else, for a DTU scan, the
    sparse-view protocol's ``dtu_views`` (params ``data.views``), and for any other capture
    (COLMAP, nerfstudio) every image it holds (ids 0..N-1 by image name)."""
    if given:
        return [int(v) for v in given]
    if layouts.detect(src) == "dtu":
        return [int(v) for v in dtu_views]
    return sorted(layouts.read_capture(src).images)


def prepare_scene(
    src: str | Path, out: str | Path, cfg: DataConfig, name: str | None = None, extra_meta: dict | None = None,
    warn: Callable[[str], None] = print_warning, use_masks: bool = True,
    sphere: tuple[float, float, float, float] | None = None,
) -> Scene:
    """Load ``src`` at ``cfg.views`` / ``cfg.width x cfg.height`` and write it to ``out`` (a
    gcgs ``scene`` output: never the source or a folder gcgs did not write). Every check
    runs before anything is written. ``use_masks=False`` leaves the source's masks out, as
    if the capture had none (docs/inputs.md, "Without masks"). ``sphere`` = (cx, cy, cz,
    radius) in the input's world frame and units replaces the unit sphere (``scale_mat``) the
    layout gives or derives (docs/inputs.md, "Units and the unit sphere")."""
    src = Path(src)
    extra_meta = dict(extra_meta or {})
    if not use_masks:
        extra_meta["masks_ignored"] = True
    with atomic_dir(out, "scene", inputs=(src,)) as tmp:
        if layouts.detect(src) != "dtu":
            cap = layouts.read_capture(src)
            if not use_masks:
                cap.masks = None
            if sphere is not None:
                cap.cameras.norm_to_world = given_sphere(sphere, cap.cameras.world_to_cam, cfg.views, src)
                cap.notes["scale_mat"] = _given_note(sphere)
            scene = _prepare_capture(cap, tmp, cfg, name, extra_meta, warn)
        else:
            scene = _prepare_dtu(src, tmp, cfg, name, extra_meta, warn, use_masks, sphere)
    return scene


def given_sphere(sphere, world_to_cam: dict[int, np.ndarray], views, src: Path) -> np.ndarray:
    """The ``scale_mat`` of a sphere given as (cx, cy, cz, radius) in world units, checked:
    finite, a positive radius, its centre in front of every training view's camera."""
    vals = np.asarray(sphere, np.float64).reshape(-1)
    if vals.shape != (4,) or not np.all(np.isfinite(vals)) or vals[3] <= 0:
        raise SceneError(f"{src}: the given sphere must be four finite numbers CX CY CZ RADIUS with RADIUS > 0, "
                         f"got {list(sphere)}")
    centre = vals[:3]
    for v in views:
        T = world_to_cam[v]
        if (T[:3, :3] @ centre + T[:3, 3])[2] <= 0:
            raise SceneError(f"{src}: the given sphere's centre {centre.tolist()} is behind view {v}'s camera")
    S = sphere_matrix(centre, float(vals[3]))
    if problem := dtu.scale_mat_problem(S):
        raise SceneError(f"{src}: the given sphere {list(sphere)} makes a scale_mat that {problem}, which "
                         "gcgs init would refuse; give the radius in the input's world units")
    return S


def _given_note(sphere) -> str:
    cx, cy, cz, r = (float(x) for x in sphere)
    return f"given (gcgs prepare --sphere): centre ({cx:g}, {cy:g}, {cz:g}), radius {r:g}, world units"


def _check_views(src: Path, cfg: DataConfig) -> None:
    if len(cfg.views) < MIN_VIEWS:
        raise SceneError(f"data.views: {cfg.views} selects {len(cfg.views)} view of {src}; the method needs at "
                         f"least {MIN_VIEWS} (it triangulates between views)")


def _prepare_dtu(src: Path, tmp: Path, cfg: DataConfig, name: str | None, extra_meta: dict | None,
                 warn: Callable[[str], None], use_masks: bool = True,
                 sphere: tuple[float, float, float, float] | None = None) -> Scene:
    stored_w, stored_h = dtu.stored_image_size(src)  # all cameras are for this size
    check_aspect(src, (stored_w, stored_h), cfg.width, cfg.height)
    check_size(src, (stored_w, stored_h), cfg.width, cfg.height, warn)
    _check_views(src, cfg)
    scene = dtu.load_scene(src, view_ids=cfg.views, resolution=(cfg.width, cfg.height), name=name,
                           with_masks=use_masks)
    if scene.masks is not None:
        for v, m in zip(scene.view_ids, scene.masks):
            if not m.any():
                raise SceneError(f"{src / 'mask'}: the mask of view {v} covers no pixel at {cfg.width}x{cfg.height}")
    cams = dtu.load_cameras(src)
    norm_to_world = cams.norm_to_world
    if sphere is not None:
        norm_to_world = given_sphere(sphere, cams.world_to_cam, cfg.views, src)
        extra_meta = {**(extra_meta or {}), "scale_mat": _given_note(sphere)}
        scene = dataclasses.replace(scene, norm_to_world=norm_to_world)
    sx, sy = cfg.width / stored_w, cfg.height / stored_h
    K = {v: geometry.scale_intrinsics(cams.K[v], sx, sy) for v in cams.ids}
    masks = None
    if scene.masks is not None:
        masks = dtu.load_masks(src, size=(cfg.width, cfg.height))
    meta = dict(scene.meta)
    meta.update(
        name=scene.name,
        scan_id=scene.scan_id,
        prepared_from=str(src),
        views=scene.view_ids,
        width=cfg.width,
        height=cfg.height,
        **(extra_meta or {}),
    )
    dtu.write_scene_files(
        tmp,
        images=dict(zip(scene.view_ids, scene.images)),
        K=K,
        world_to_cam=cams.world_to_cam,
        norm_to_world=norm_to_world,
        masks=masks,
        meta=meta,
    )
    return scene


def _prepare_capture(cap: Capture, tmp: Path, cfg: DataConfig, name: str | None, extra_meta: dict | None,
                     warn: Callable[[str], None]) -> Scene:
    """The COLMAP / nerfstudio path: the same checks and the same DTU-layout output as a DTU
    scan's, from undistorted pinhole images."""
    W, H = cfg.width, cfg.height
    check_aspect(cap.root, cap.size, W, H)
    check_size(cap.root, cap.size, W, H, warn)
    _check_views(cap.root, cfg)
    views = [int(v) for v in cfg.views]
    for v in views:
        if v not in cap.images:
            raise SceneError(f"{cap.image_dir}: view {v} requested but the capture has views 0..{len(cap.images) - 1} "
                             "(its images sorted by name)")
    sx, sy = W / cap.size[0], H / cap.size[1]
    K = {v: geometry.scale_intrinsics(cap.cameras.K[v], sx, sy) for v in cap.cameras.ids}
    images = {v: _resize(cap.read_image(v), W, H) for v in views}
    masks = None
    if cap.masks is not None:
        masks = {}
        for v in sorted(cap.masks):
            m = cap.read_mask(v)
            if v in views and not m.any():
                raise SceneError(f"{cap.masks[v]}: mask is empty (no foreground pixel)")
            masks[v] = dtu.resize_mask(m, W, H)
            if v in views and not masks[v].any():
                raise SceneError(f"{cap.masks[v]}: the mask of view {v} covers no pixel at {W}x{H}")
    meta = dict(cap.notes)
    meta.update(name=name or cap.root.name, scan_id=None, prepared_from=str(cap.root), views=views, width=W,
                height=H, units="the input's world frame and units (lengths named mm are in these units)",
                **(extra_meta or {}))
    dtu.write_scene_files(tmp, images=images, K=K, world_to_cam=cap.cameras.world_to_cam,
                          norm_to_world=cap.cameras.norm_to_world, masks=masks, meta=meta)
    return Scene(name=meta["name"], images=np.stack([images[v] for v in views]).astype(np.float32),
                 masks=None if masks is None else np.stack([masks[v] for v in views]),
                 K=np.stack([K[v] for v in views]), world_to_cam=np.stack([cap.cameras.world_to_cam[v] for v in views]),
                 norm_to_world=cap.cameras.norm_to_world, view_ids=views, source=cap.root, meta=meta)


def _resize(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """As :func:`dtu.load_scene` resizes: area when shrinking, linear when enlarging."""
    if img.shape[:2] == (height, width):
        return img
    interp = cv2.INTER_AREA if width < img.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(img, (width, height), interpolation=interp)
