"""Preparing a DTU-layout scan for training: the selected views at the training size,
with every camera and mask of the source kept (so held-out views stay usable for mask
culling and checks), all scaled to the new size. The aspect ratio is never changed.
"""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from pipeline import geometry
from pipeline.atomic import atomic_dir
from pipeline.config import DataConfig
from pipeline.data import dtu
from pipeline.data.scene import Scene, SceneError
from pipeline.errors import print_warning

MIN_VIEWS = 2
MIN_SIDE_PX = 16  # below this no NCC patch or SSIM window fits
MAX_UPSAMPLE = 4.0  # beyond this a typo (--width 100000) rather than a choice


def height_for_width(src: str | Path, width: int) -> int:
    """Training height that keeps the aspect ratio of ``src``'s images at ``width``."""
    src_w, src_h = dtu.stored_image_size(src)
    return max(1, round(width * src_h / src_w))


def check_aspect(src: str | Path, width: int, height: int) -> None:
    """Refuse a training size whose aspect ratio differs from the source images' by more
    than the rounding of the height to whole pixels (resizing would squash the image)."""
    src_w, src_h = dtu.stored_image_size(src)
    if abs(height - width * src_h / src_w) >= 1.0:
        raise SceneError(
            f"{dtu.find_image_dir(src)}: source images are {src_w}x{src_h} (aspect {src_w / src_h:.3f}) but the "
            f"training size {width}x{height} has aspect {width / height:.3f}; resizing would squash them. "
            f"Give --width alone (the height follows: {height_for_width(src, width)} at width {width}) or "
            "set data.width and data.height in the source's aspect"
        )


def check_size(src: Path, stored: tuple[int, int], width: int, height: int, warn: Callable[[str], None]) -> None:
    """Refuse a training size too small to hold a patch or more than
    :data:`MAX_UPSAMPLE` times the source; warn when it upsamples (no detail is gained)."""
    where = dtu.find_image_dir(src)
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


def prepare_scene(
    src: str | Path, out: str | Path, cfg: DataConfig, name: str | None = None, extra_meta: dict | None = None,
    warn: Callable[[str], None] = print_warning,
) -> Scene:
    """Load ``src`` at ``cfg.views`` / ``cfg.width x cfg.height`` and write it to ``out`` (a
    gcgs ``scene`` output: never the source or a folder gcgs did not write). Every check
    runs before anything is written."""
    src = Path(src)
    with atomic_dir(out, "scene", inputs=(src,)) as tmp:
        stored_w, stored_h = dtu.stored_image_size(src)  # all cameras are for this size
        check_aspect(src, cfg.width, cfg.height)
        check_size(src, (stored_w, stored_h), cfg.width, cfg.height, warn)
        if len(cfg.views) < MIN_VIEWS:
            raise SceneError(f"data.views: {cfg.views} selects {len(cfg.views)} view of {src}; the method needs at "
                             f"least {MIN_VIEWS} (it triangulates between views)")
        scene = dtu.load_scene(src, view_ids=cfg.views, resolution=(cfg.width, cfg.height), name=name)
        if scene.masks is not None:
            for v, m in zip(scene.view_ids, scene.masks):
                if not m.any():
                    raise SceneError(f"{src / 'mask'}: the mask of view {v} covers no pixel at {cfg.width}x{cfg.height}")
        cams = dtu.load_cameras(src)
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
            norm_to_world=cams.norm_to_world,
            masks=masks,
            meta=meta,
        )
    return scene
