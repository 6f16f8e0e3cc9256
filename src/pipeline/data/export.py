"""Writers of the COLMAP and nerfstudio layouts (the inverse of :mod:`pipeline.data.colmap` and
:mod:`pipeline.data.nerfstudio`): the same views, cameras and masks as a DTU-layout scan,
so that one scene can be prepared from every layout `gcgs prepare` reads
(``gcgs bench-layouts``, tests/test_layouts.py, docs/inputs.md).

Frames and conventions. Input cameras are this project's: OpenCV world-to-camera (x right,
y down, z forward) in the scan's world frame and units (DTU: mm), intrinsics with pixel
centres at integer coordinates. Both layouts are written in the **same world frame and
units** (nothing is re-centred or re-scaled); their own conventions are applied on the way
out, as the readers undo them:

* pixel centres at +0.5 (COLMAP and nerfstudio): ``cx_out = cx + 0.5``, ``cy_out = cy + 0.5``;
  focal lengths unchanged;
* COLMAP: one camera per view (``PINHOLE`` ``fx fy cx cy``), the image's pose is
  world-to-camera (``cam_from_world``) as given; written by pycolmap (``sparse/0/``, text
  or binary);
* nerfstudio: ``transform_matrix`` is camera-to-world in OpenGL axes (x right, y up, z
  backward): ``inverse(world_to_cam) @ diag(1, -1, -1, 1)``; ``camera_model: OPENCV`` with
  no distortion.

Neither layout has a skew term: a camera's ``K[0, 1]`` (DTU decompositions keep a tiny one)
is dropped; the largest pixel shift this causes is returned (``skew_dropped_px``).

View ids: both readers number views by the images sorted by name, so a scan's views must be
numbered 0..N-1 (those with an image; cameras of views without one are not written) and the
names are zero-padded to sort in that order.
"""
from __future__ import annotations

import json
import shutil
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from pipeline import geometry
from pipeline.atomic import atomic_dir
from pipeline.data import dtu
from pipeline.data.nerfstudio import FILE as NERFSTUDIO_FILE
from pipeline.data.nerfstudio import GL_TO_CV
from pipeline.data.scene import SceneError

KIND = "capture"  # the atomic output kind of an exported folder
PIXEL_CENTRE = 0.5  # COLMAP's and nerfstudio's pixel centres, relative to this project's
ImageSource = Path | np.ndarray  # a file (copied byte for byte) or an RGB / bool array (written as PNG)


# ---- shared helpers -------------------------------------------------------------------


def _put_image(src: ImageSource, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(src, (str, Path)):
        shutil.copyfile(src, dst)  # the same bytes: the same pixels for every reader
    else:
        dtu._write_png(dst, np.asarray(src))  # bool masks become 0 / 255


def _suffix(src: ImageSource) -> str:
    return Path(src).suffix.lower() if isinstance(src, (str, Path)) else ".png"


def _check_views(images: Mapping[int, ImageSource], K: Mapping[int, np.ndarray], where: str,
                 masks: Mapping[int, ImageSource] | None = None) -> list[int]:
    views = sorted(int(v) for v in images)
    if views != list(range(len(views))):
        raise SceneError(f"{where}: views {views[:8]}... are not numbered 0..{len(views) - 1}; COLMAP and nerfstudio "
                         "number views by the sorted image names, so the view ids would change")
    missing = [v for v in views if v not in K]
    if missing:
        raise SceneError(f"{where}: no camera for views {missing[:5]}")
    for v in views if masks else ():
        if v not in masks:
            raise SceneError(f"{where}: no mask for view {v} (a capture has a mask for every view or none)")
    return views


def _skew_px(K: np.ndarray, size: tuple[int, int]) -> float:
    """The largest pixel shift from dropping ``K[0, 1]`` inside a ``size`` image."""
    h = size[1]
    return abs(float(K[0, 1])) * max(abs(K[1, 2]), abs(h - 1 - K[1, 2])) / float(K[1, 1])


def _names(views: list[int], fmt: Callable[[int, int], str]) -> dict[int, str]:
    width = max(4, len(str(max(views))))
    return {v: fmt(v, width) for v in views}


# ---- COLMAP ---------------------------------------------------------------------------


def colmap_reconstruction(K: Mapping[int, np.ndarray], world_to_cam: Mapping[int, np.ndarray], size: tuple[int, int],
                          names: Mapping[int, str], points_world: np.ndarray | None = None,
                          camera_model: str = "PINHOLE", extra_params: tuple[float, ...] = (),
                          image_ids: Mapping[int, int] | None = None):
    """A ``pycolmap.Reconstruction`` of the views ``names`` (view id -> image name): camera
    ``v + 1`` per view with ``camera_model`` (``PINHOLE``: ``fx fy cx+0.5 cy+0.5``;
    ``SIMPLE_PINHOLE``: ``f cx+0.5 cy+0.5``, needs ``fx == fy``; another model: ``fx fy cx+0.5
    cy+0.5`` followed by ``extra_params``, e.g. ``OPENCV``'s ``k1 k2 p1 p2``), the image's
    pose ``world_to_cam`` (world frame and units kept), image id ``image_ids[v]`` (default
    ``v + 1``). ``points_world`` (N, 3) become ``points3D``, each with a track of the views
    whose image it projects into (in front of the camera): the observations a structure-from-
    motion model would have, without occlusion (pass visible points, :func:`pipeline.benchmarks.layouts.seen_points`)."""
    import pycolmap  # heavy; only COLMAP needs it

    W, H = size
    rec = pycolmap.Reconstruction()
    views = sorted(names)
    ids = {v: (v + 1 if image_ids is None else int(image_ids[v])) for v in views}
    pts = np.zeros((0, 3)) if points_world is None else np.asarray(points_world, np.float64).reshape(-1, 3)
    seen_by: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for v in views:
        k = np.asarray(K[v], np.float64)
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2] + PIXEL_CENTRE, k[1, 2] + PIXEL_CENTRE
        if camera_model == "SIMPLE_PINHOLE":
            if abs(fx - fy) > 1e-9 * fx:
                raise ValueError(f"view {v}: SIMPLE_PINHOLE needs fx == fy, got {fx} and {fy}")
            params = [fx, cx, cy]
        else:
            params = [fx, fy, cx, cy, *extra_params]
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model=camera_model, width=W, height=H, params=params,
                                                        camera_id=v + 1))
        px, z = geometry.project(k, world_to_cam[v], pts) if len(pts) else (np.zeros((0, 2)), np.zeros(0))
        inside = (z > 0) & np.all(px >= -0.5, 1) & (px[:, 0] < W - 0.5) & (px[:, 1] < H - 0.5)
        idx = np.flatnonzero(inside)
        seen_by[v] = (idx, px[idx] + PIXEL_CENTRE)  # keypoints in COLMAP's pixel convention
        T = np.asarray(world_to_cam[v], np.float64)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(T[:3, :3]), T[:3, 3])
        rec.add_image_with_trivial_frame(pycolmap.Image(name=names[v], keypoints=seen_by[v][1], camera_id=v + 1,
                                                        image_id=ids[v]), pose)
    tracks: list[list[tuple[int, int]]] = [[] for _ in range(len(pts))]
    for v in views:
        for j, i in enumerate(seen_by[v][0]):
            tracks[i].append((ids[v], j))
    grey = np.array([128, 128, 128], np.uint8)
    for p, elements in zip(pts, tracks):
        track = pycolmap.Track()
        for image_id, j in elements:
            track.add_element(image_id, j)
        rec.add_point3D(p, track, grey)
    return rec


def write_colmap(out_dir: str | Path, K: Mapping[int, np.ndarray], world_to_cam: Mapping[int, np.ndarray],
                 size: tuple[int, int], images: Mapping[int, ImageSource],
                 masks: Mapping[int, ImageSource] | None = None, points_world: np.ndarray | None = None, *,
                 binary: bool = False, camera_model: str = "PINHOLE", extra_params: tuple[float, ...] = (),
                 mask_naming: str = "colmap", image_ids: Mapping[int, int] | None = None,
                 inputs: tuple[str | Path, ...] = ()) -> dict:
    """Write a COLMAP capture into ``out_dir`` (a new or empty folder, written whole or not at
    all): ``images/NNNN.ext`` (view ``v`` at ``images[v]``: a file copied as it is, or an
    RGB array written as PNG), ``sparse/0/`` (pycolmap's text or ``binary`` writer, see
    :func:`colmap_reconstruction`) and, with ``masks``, ``masks/NNNN.ext.png`` (COLMAP's
    ``--ImageReader.mask_path`` naming; ``mask_naming="stem"``: ``masks/NNNN.png``), grey 255
    on the object. Cameras of views without an image are not written. A non-pinhole
    ``camera_model`` only labels the images: they must already have that lens. Returns
    facts (views, names, points, ``skew_dropped_px``)."""
    views = _check_views(images, K, str(out_dir), masks)
    names = _names(views, lambda v, w: f"{v:0{w}d}{_suffix(images[v])}")
    with atomic_dir(out_dir, KIND, inputs=inputs) as tmp:
        for v in views:
            _put_image(images[v], tmp / "images" / names[v])
        if masks:
            for v in views:
                name = f"{names[v]}.png" if mask_naming == "colmap" else f"{Path(names[v]).stem}.png"
                _put_mask(masks[v], tmp / "masks" / name)
        rec = colmap_reconstruction(K, world_to_cam, size, names, points_world, camera_model, extra_params, image_ids)
        model = tmp / "sparse" / "0"
        model.mkdir(parents=True)
        (rec.write_binary if binary else rec.write_text)(str(model))
    return {"layout": "colmap", "binary": binary, "views": views, "names": [names[v] for v in views],
            "points3D": 0 if points_world is None else len(points_world),
            "skew_dropped_px": max(_skew_px(K[v], size) for v in views)}


def _put_mask(src: ImageSource, dst: Path) -> None:
    """A mask as PNG, grey 255 on the object (> 127 in the source, as :func:`dtu.read_mask`)."""
    m = dtu.read_mask(Path(src)) if isinstance(src, (str, Path)) else np.asarray(src).astype(bool)
    _put_image(m, dst)


# ---- nerfstudio -----------------------------------------------------------------------


def camera_to_world_gl(world_to_cam: np.ndarray) -> np.ndarray:
    """nerfstudio's ``transform_matrix``: camera-to-world with OpenGL camera axes."""
    return geometry.rigid_inverse(np.asarray(world_to_cam, np.float64)) @ GL_TO_CV


def _intrinsics(k: np.ndarray, size: tuple[int, int]) -> dict:
    return {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]) + PIXEL_CENTRE,
            "cy": float(k[1, 2]) + PIXEL_CENTRE, "w": int(size[0]), "h": int(size[1])}


def write_nerfstudio(out_dir: str | Path, K: Mapping[int, np.ndarray], world_to_cam: Mapping[int, np.ndarray],
                     size: tuple[int, int], images: Mapping[int, ImageSource],
                     masks: Mapping[int, ImageSource] | None = None, *, per_frame: bool | None = None,
                     distortion: Mapping[str, float] | None = None, inputs: tuple[str | Path, ...] = ()) -> dict:
    """Write a nerfstudio capture into ``out_dir`` (a new or empty folder, written whole or
    not at all): ``transforms.json`` (``camera_model: OPENCV``; per frame ``file_path``
    ``images/frame_NNNNN.ext``, ``transform_matrix`` = :func:`camera_to_world_gl`, and with
    ``masks`` a ``mask_path`` ``masks/frame_NNNNN.png``) beside the images (files copied as
    they are, arrays written as PNG). Intrinsics ``fl_x fl_y cx+0.5 cy+0.5 w h`` go in each
    frame when ``per_frame`` (default: when the views' intrinsics differ), else once at the
    top level; ``distortion`` (``k1 k2 p1 p2 k3``) is written at the top level as given (the
    images must already have that lens). Returns facts as :func:`write_colmap`."""
    views = _check_views(images, K, str(out_dir), masks)
    if per_frame is None:
        per_frame = any(not np.array_equal(K[v], K[views[0]]) for v in views)
    names = _names(views, lambda v, w: f"frame_{v:0{max(w, 5)}d}")
    frames = []
    with atomic_dir(out_dir, KIND, inputs=inputs) as tmp:
        for v in views:
            f = {"file_path": f"images/{names[v]}{_suffix(images[v])}",
                 "transform_matrix": camera_to_world_gl(world_to_cam[v]).tolist()}
            _put_image(images[v], tmp / f["file_path"])
            if masks:
                f["mask_path"] = f"masks/{names[v]}.png"
                _put_mask(masks[v], tmp / f["mask_path"])
            if per_frame:
                f.update(_intrinsics(K[v], size))
            frames.append(f)
        meta: dict = {"camera_model": "OPENCV"}
        if not per_frame:
            meta.update(_intrinsics(K[views[0]], size))
        meta.update(distortion or {})
        meta["frames"] = frames
        (tmp / NERFSTUDIO_FILE).write_text(json.dumps(meta, indent=2) + "\n")
    return {"layout": "nerfstudio", "views": views, "names": [f["file_path"] for f in frames], "per_frame": per_frame,
            "skew_dropped_px": max(_skew_px(K[v], size) for v in views)}


# ---- from a DTU-layout scan -------------------------------------------------------------


def _dtu_views(dtu_dir: Path) -> tuple[dtu.DTUCameras, dict[int, Path], dict[int, Path] | None, tuple[int, int]]:
    cams = dtu.load_cameras(dtu_dir)
    images = dtu._numbered_files(dtu.find_image_dir(dtu_dir))
    if not dtu._named_by_number(images.values()):
        raise SceneError(f"{dtu.find_image_dir(dtu_dir)}: image names are not view numbers")
    mask_dir = dtu_dir / "mask"
    masks = dtu._numbered_files(mask_dir) if mask_dir.is_dir() else None
    return cams, images, masks, dtu.stored_image_size(dtu_dir)


def export_colmap(dtu_dir: str | Path, out_dir: str | Path, binary: bool, points_world: np.ndarray | None = None,
                  ) -> dict:
    """Write the DTU-layout scan ``dtu_dir`` (``image/``, ``mask/``, ``cameras_sphere.npz``)
    as a COLMAP capture in ``out_dir`` (:func:`write_colmap`): the same image files, masks
    as ``masks/NAME.png``, a ``PINHOLE`` camera per view (+0.5 pixel centres), poses in the
    scan's world frame and units (DTU: mm).

    ``points_world`` (N, 3, world units) stand in for the structure-from-motion points a
    real COLMAP model has (e.g. :func:`pipeline.benchmarks.layouts.seen_points` of the
    ground truth's points); ``None`` writes an empty ``points3D``. The reader places its unit
    sphere where the cameras look, and around these points only when the cameras' optical
    axes do not meet (:mod:`pipeline.data.colmap`)."""
    dtu_dir = Path(dtu_dir)
    cams, images, masks, size = _dtu_views(dtu_dir)
    info = write_colmap(out_dir, cams.K, cams.world_to_cam, size, images, masks, points_world, binary=binary,
                        inputs=(dtu_dir,))
    return {**info, "source": str(dtu_dir)}


def export_nerfstudio(dtu_dir: str | Path, out_dir: str | Path) -> dict:
    """Write the DTU-layout scan ``dtu_dir`` as a nerfstudio capture in ``out_dir``
    (:func:`write_nerfstudio`): the same image files, ``mask_path`` per frame, OpenGL
    camera-to-world ``transform_matrix`` in the scan's world frame and units (DTU: mm),
    ``fl_x fl_y cx cy w h`` (+0.5 pixel centres) per frame when the views' intrinsics
    differ. No points: the reader's unit sphere comes from the cameras
    (:func:`pipeline.data.capture.sphere_from_cameras`)."""
    dtu_dir = Path(dtu_dir)
    cams, images, masks, size = _dtu_views(dtu_dir)
    info = write_nerfstudio(out_dir, cams.K, cams.world_to_cam, size, images, masks, inputs=(dtu_dir,))
    return {**info, "source": str(dtu_dir)}
