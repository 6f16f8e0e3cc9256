"""Reader for a nerfstudio capture: ``transforms.json`` beside the images it names.

Each frame has ``file_path`` (relative to the JSON's folder), ``transform_matrix``
(camera-to-world in OpenGL axes: x right, y up, z backward) and optionally ``mask_path``;
the intrinsics ``fl_x, fl_y, cx, cy, w, h`` (and distortion ``k1 k2 k3 p1 p2``) are given
once at the top level or per frame. nerfstudio puts pixel centres at +0.5, this project at
integer coordinates: ``cx = cx_nerfstudio - 0.5``. View ids are the frames sorted by
``file_path``: 0, 1, 2, ... The unit sphere (``scale_mat``) is where the cameras look
(:func:`capture.sphere_from_cameras`).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from pipeline.data import dtu
from pipeline.data.capture import Capture, Undistort, common_size, sphere_from_cameras, sphere_matrix
from pipeline.data.scene import SceneError

FILE = "transforms.json"
INTRINSICS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips y and z: OpenGL camera axes -> OpenCV's


def is_nerfstudio(root: Path) -> bool:
    return (root / FILE).is_file()


def _number(path: Path, where: str, key: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if not math.isfinite(x):
        raise SceneError(f"{path}: {where}: {key} must be a finite number, got {value!r}")
    return x


def read_capture(root: str | Path) -> Capture:
    """Read a nerfstudio capture folder (see the module doc)."""
    root = Path(root)
    path = root / FILE
    try:
        meta = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SceneError(f"{path}: cannot read ({exc})") from exc
    frames = meta.get("frames") if isinstance(meta, dict) else None
    if not isinstance(frames, list) or not frames:
        raise SceneError(f"{path}: no \"frames\" list")
    model = meta.get("camera_model", "OPENCV")
    if model != "OPENCV":
        raise SceneError(f"{path}: camera_model {model!r} is not supported (only OPENCV, the pinhole with "
                         "k1 k2 k3 p1 p2)")
    for i, f in enumerate(frames):
        if not isinstance(f, dict) or not isinstance(f.get("file_path"), str):
            raise SceneError(f"{path}: frame {i} has no \"file_path\"")
    frames = sorted(frames, key=lambda f: f["file_path"])
    with_masks = [("mask_path" in f) for f in frames]
    if any(with_masks) and not all(with_masks):
        missing = frames[with_masks.index(False)]["file_path"]
        raise SceneError(f"{path}: frame {missing!r} has no mask_path while others have one; give every frame "
                         "a mask or none")

    K, w2c, images, masks, undistort, sizes = {}, {}, {}, {}, {}, {}
    for v, f in enumerate(frames):
        where = f"frame {f['file_path']!r}"
        missing = [k for k in INTRINSICS if k not in f and k not in meta]
        if missing:
            raise SceneError(f"{path}: {where}: no intrinsics {', '.join(missing)} (neither in the frame nor at "
                             "the top level)")
        fx, fy, cx, cy, w, h = (_number(path, where, k, f.get(k, meta.get(k))) for k in INTRINSICS)
        if fx <= 0 or fy <= 0 or w < 1 or h < 1:
            raise SceneError(f"{path}: {where}: focal lengths and size must be positive")
        dist = [_number(path, where, k, f.get(k, meta.get(k, 0.0))) for k in DISTORTION]
        try:
            c2w = np.asarray(f["transform_matrix"], np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise SceneError(f"{path}: {where}: no transform_matrix ({exc})") from exc
        if c2w.shape == (3, 4):
            c2w = np.vstack([c2w, [0.0, 0.0, 0.0, 1.0]])
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise SceneError(f"{path}: {where}: transform_matrix must be a finite 4x4 (or 3x4) matrix")
        R = c2w[:3, :3]
        scale = np.cbrt(np.linalg.det(R))
        if not np.allclose(R.T @ R, np.eye(3) * scale * scale, atol=1e-5) or scale <= 0:
            raise SceneError(f"{path}: {where}: transform_matrix's rotation is not a rotation")
        c2w_cv = c2w @ GL_TO_CV
        c2w_cv[:3, :3] /= scale  # tolerate a uniformly scaled export; the centre is kept
        T = np.eye(4)
        T[:3, :3] = c2w_cv[:3, :3].T
        T[:3, 3] = -c2w_cv[:3, :3].T @ c2w_cv[:3, 3]
        K[v] = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        if any(d != 0.0 for d in dist):
            undistort[v] = Undistort(K[v], np.asarray(dist, np.float64))
        w2c[v] = T
        images[v] = _file(root, path, where, f["file_path"])
        sizes[where] = (int(round(w)), int(round(h)))
        if all(with_masks):
            masks[v] = _file(root, path, where, f["mask_path"])
    size = common_size(sizes, path)
    try:
        centre, radius = sphere_from_cameras(K, w2c, size)
    except SceneError as exc:
        raise SceneError(f"{path}: {exc}") from exc
    cams = dtu.DTUCameras(K=K, world_to_cam=w2c, norm_to_world=sphere_matrix(centre, radius), path=path)
    return Capture(layout="nerfstudio", root=root, cameras=cams, images=images, masks=masks or None, size=size,
                   image_dir=root, mask_dir=root if masks else None, undistort=undistort,
                   notes={"layout": "nerfstudio", "scale_mat": "sphere where the cameras' optical axes meet, holding every view's frame",
                          "view_names": [f["file_path"] for f in frames]})


def _file(root: Path, path: Path, where: str, rel) -> Path:
    if not isinstance(rel, str):
        raise SceneError(f"{path}: {where}: file path {rel!r} is not a string")
    p = root / rel
    if not p.is_file():
        raise SceneError(f"{path}: {where}: file {p} not found")
    return p
