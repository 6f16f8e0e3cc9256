"""Preparing a DTU-layout scan for training: the selected views at the training size,
with every camera and mask of the source kept (so held-out views stay usable for mask
culling and checks), all scaled to the new size. The aspect ratio is never changed.
"""
from __future__ import annotations

from pathlib import Path

from pipeline import geometry
from pipeline.config import DataConfig
from pipeline.data import dtu
from pipeline.data.scene import Scene, SceneError


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
            f"{dtu.first_image(src)}: source images are {src_w}x{src_h} (aspect {src_w / src_h:.3f}) but the "
            f"training size {width}x{height} has aspect {width / height:.3f}; resizing would squash them. "
            f"Give --width alone (the height follows: {height_for_width(src, width)} at width {width}) or "
            "set data.width and data.height in the source's aspect"
        )


def prepare_scene(
    src: str | Path, out: str | Path, cfg: DataConfig, name: str | None = None, extra_meta: dict | None = None
) -> Scene:
    """Load ``src`` at ``cfg.views`` / ``cfg.width x cfg.height`` and write it to ``out``."""
    src = Path(src)
    check_aspect(src, cfg.width, cfg.height)
    scene = dtu.load_scene(src, view_ids=cfg.views, resolution=(cfg.width, cfg.height), name=name)
    cams = dtu.load_cameras(src)
    # All cameras share the stored image size of the source; scale every one like the views.
    stored_w, stored_h = dtu.stored_image_size(src)
    sx, sy = cfg.width / stored_w, cfg.height / stored_h
    K = {v: geometry.scale_intrinsics(cams.K[v], sx, sy) for v in cams.ids}
    masks = None
    if scene.masks is not None:
        masks = {v: dtu.resize_mask(m, cfg.width, cfg.height) for v, m in dtu.load_masks(src).items()}
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
    dtu.write_scene(
        out,
        images=dict(zip(scene.view_ids, scene.images)),
        K=K,
        world_to_cam=cams.world_to_cam,
        norm_to_world=cams.norm_to_world,
        masks=masks,
        meta=meta,
    )
    return scene
