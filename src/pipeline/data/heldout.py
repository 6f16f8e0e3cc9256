"""Held-out views: the views of a scan not used for training, at a reduced size, for
judging a reconstruction where no ground-truth geometry exists (mask IoU, masked PSNR).

A scan may carry them in ``SRC/heldout/`` (a DTU-layout scan of its own: the bundled scan24
keeps its 46 held-out views there at 200x150, since its ``image/`` holds only the inputs);
otherwise they are read from ``SRC/image/`` itself (synthetic scenes render all 49 views).
"""
from __future__ import annotations

from pathlib import Path

from pipeline.data import dtu
from pipeline.data.scene import Scene, SceneError

HELDOUT_DIR = "heldout"


def write_heldout(src: str | Path, out: str | Path, train_views: list[int], width: int, height: int) -> Path:
    """Write every view of ``src`` except ``train_views`` at ``width x height`` as a scan."""
    full = dtu.load_scene(src, view_ids=None, resolution=(width, height))
    keep = [i for i, v in enumerate(full.view_ids) if v not in set(train_views)]
    ids = [full.view_ids[i] for i in keep]
    return dtu.write_scene(
        out, images={v: full.images[i] for v, i in zip(ids, keep)}, K={v: full.K[i] for v, i in zip(ids, keep)},
        world_to_cam={v: full.world_to_cam[i] for v, i in zip(ids, keep)}, norm_to_world=full.norm_to_world,
        masks={v: full.masks[i] for v, i in zip(ids, keep)} if full.masks is not None else None,
        meta={"held_out_from": Path(src).name, "train_views": list(train_views), "width": width, "height": height})


def load_heldout(src: str | Path, train_views: list[int], width: int) -> Scene:
    """The held-out views of ``src`` at ``width`` pixels wide (aspect kept), with masks."""
    src = Path(src)
    root = src / HELDOUT_DIR if (src / HELDOUT_DIR).is_dir() else src
    w0, h0 = dtu.stored_image_size(root)
    height = max(1, round(width * h0 / w0))
    ids = [v for v in dtu.image_ids(root) if v not in set(train_views)]
    if not ids:
        raise SceneError(f"{root}: no held-out view (every image is a training view)")
    scene = dtu.load_scene(root, view_ids=ids, resolution=(width, height))
    if scene.masks is None:
        raise SceneError(f"{root}: held-out views need masks (mask/) for the IoU")
    return scene
