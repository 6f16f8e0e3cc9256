"""Reader for a COLMAP capture: ``images/`` plus a sparse model in ``sparse/0/`` (or
``sparse/``), text (``cameras.txt``, ``images.txt``, ``points3D.txt``) or binary
(``.bin``), read with pycolmap; optional masks ``masks/NAME.png`` (COLMAP's
``--ImageReader.mask_path`` naming, ``masks/0001.jpg.png``) or ``masks/0001.png``.

View ids are the model's posed images sorted by name: 0, 1, 2, ... Camera models
PINHOLE and SIMPLE_PINHOLE are used as they are; SIMPLE_RADIAL, RADIAL and OPENCV images
(and masks) are undistorted to the pinhole of their focal lengths and principal point at
the same size; other models are refused. COLMAP puts pixel centres at +0.5, this project
at integer coordinates: ``cx = cx_colmap - 0.5``. The unit sphere (``scale_mat``) is where
the cameras look (:func:`capture.sphere_from_cameras`, as for nerfstudio: the sparse points
of a real capture hold its background too); around the robust extent of the model's points
(:func:`capture.sphere_from_points`) when the optical axes do not meet.
"""
from __future__ import annotations

import functools
import re
import struct
from pathlib import Path

import numpy as np

from pipeline.data import dtu
from pipeline.data.capture import Capture, Undistort, common_size, sphere_from_cameras, sphere_from_points, sphere_matrix
from pipeline.data.scene import SceneError

MODEL_DIRS = ("sparse/0", "sparse")
MODEL_FILES = ("cameras", "images", "points3D")
# model -> (fx, fy, cx, cy, OpenCV distortion k1 k2 p1 p2) from COLMAP's params
PINHOLE_MODELS = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], None),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], None),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], 0.0, 0.0, 0.0]),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], [p[3], p[4], 0.0, 0.0]),
    "OPENCV": lambda p: (p[0], p[1], p[2], p[3], list(p[4:8])),
}
MIN_POINTS = 10  # fewer sparse points than this say little about where the object is


def find_model(root: Path) -> Path | None:
    """The folder holding the sparse model (text or binary), ``None`` without one."""
    for sub in MODEL_DIRS:
        d = root / sub
        for ext in (".bin", ".txt"):
            if all((d / f"{name}{ext}").is_file() for name in MODEL_FILES):
                return d
    return None


def is_colmap(root: Path) -> bool:
    return (root / "images").is_dir() and find_model(root) is not None


def _model_file(model: Path, name: str) -> Path:
    return model / f"{name}.bin" if (model / f"{name}.bin").is_file() else model / f"{name}.txt"


def read_capture(root: str | Path) -> Capture:
    """Read a COLMAP capture folder (see the module doc)."""
    import pycolmap  # heavy; only COLMAP captures need it

    root = Path(root)
    model = find_model(root)
    if model is None:
        raise SceneError(f"{root}: no COLMAP model (expected {' or '.join(MODEL_DIRS)}/ with "
                         "cameras, images, points3D as .txt or .bin)")
    check_model_files(model)
    try:
        rec = pycolmap.Reconstruction(str(model))
    except (ValueError, RuntimeError, IndexError) as exc:  # pycolmap's errors for what passes the checks
        raise SceneError(f"{model}: cannot read the COLMAP model ({' '.join(str(exc).split())})") from exc

    posed = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if not posed:
        raise SceneError(f"{_model_file(model, 'images')}: no image with a pose")
    image_dir = root / "images"
    mask_dir = root / "masks" if (root / "masks").is_dir() else None
    K, w2c, images, masks, undistort, sizes = {}, {}, {}, {}, {}, {}
    cameras_file = _model_file(model, "cameras")
    for v, im in enumerate(posed):
        path = image_dir / im.name
        if not path.is_file():
            raise SceneError(f"{_model_file(model, 'images')}: image {im.name!r} (id {im.image_id}) is not in "
                             f"{image_dir}")
        cam = rec.cameras[im.camera_id]
        model_name = cam.model.name
        if model_name not in PINHOLE_MODELS:
            raise SceneError(f"{cameras_file}: camera {im.camera_id} (of {im.name}) has model {model_name}; "
                             f"supported: {', '.join(PINHOLE_MODELS)} (undistort it first, e.g. "
                             "`colmap image_undistorter`)")
        fx, fy, cx, cy, dist = PINHOLE_MODELS[model_name]([float(x) for x in cam.params])
        K[v] = np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])
        if dist is not None and any(d != 0.0 for d in dist):
            undistort[v] = Undistort(K[v], np.asarray(dist, np.float64))
        T = np.eye(4)
        T[:3, :4] = np.asarray(im.cam_from_world().matrix(), np.float64)
        w2c[v] = T
        images[v] = path
        sizes[im.name] = (int(cam.width), int(cam.height))
        if mask_dir is not None:
            masks[v] = _mask_file(mask_dir, im.name)
    size = common_size(sizes, cameras_file)

    try:
        centre, radius = sphere_from_cameras(K, w2c, size)
        how = "sphere where the cameras' optical axes meet, holding every view's frame"
    except SceneError as no_meet:
        # Forward-facing captures: the sparse points say where the scene is.
        pts = [(p.xyz, p.track.length()) for p in rec.points3D.values()]
        xyz = np.array([p for p, _ in pts], np.float64).reshape(-1, 3)
        seen = np.array([n for _, n in pts]) >= 2
        if seen.sum() >= MIN_POINTS:  # a point seen by two views is triangulated, not a guess
            xyz = xyz[seen]
        if len(xyz) < MIN_POINTS:
            raise SceneError(f"{_model_file(model, 'points3D')}: {len(xyz)} points; {no_meet}") from no_meet
        centre, radius = sphere_from_points(xyz)
        how = (f"sphere around the robust extent of {len(xyz)} points of {_model_file(model, 'points3D')} "
               "(the cameras' optical axes do not meet)")
    cams = dtu.DTUCameras(K=K, world_to_cam=w2c, norm_to_world=sphere_matrix(centre, radius), path=cameras_file)
    return Capture(layout="colmap", root=root, cameras=cams, images=images, masks=masks if mask_dir else None,
                   size=size, image_dir=image_dir, mask_dir=mask_dir, undistort=undistort,
                   notes={"layout": "colmap", "model": str(model), "scale_mat": how,
                          "view_names": [im.name for im in posed]})


def _mask_file(mask_dir: Path, name: str) -> Path:
    """COLMAP's mask naming (``NAME.png``), else the image's stem with ``.png``."""
    for cand in (mask_dir / f"{name}.png", (mask_dir / name).with_suffix(".png")):
        if cand.is_file():
            return cand
    raise SceneError(f"{mask_dir}: no mask for image {name!r} (expected {name}.png or "
                     f"{Path(name).with_suffix('.png')})")


# ---- the model's files, checked before pycolmap reads them -----------------------------
# pycolmap trusts every count in a file: a cut points3D.bin had it allocate for 13-90 s
# before a MemoryError, an empty images.bin raised IndexError, a cut cameras.bin or
# points3D.txt read as far as it went. So the model's files are walked here first (a walk,
# no values kept): every count is checked against what the file holds before it is used.


def check_model_files(model: Path) -> None:
    """Raise :class:`SceneError` naming the file where a file of the model that pycolmap will
    read (binary when all of cameras, images, points3D are; rigs and frames where present)
    holds fewer or more records than it declares, or a record lacks columns."""
    binary = all((model / f"{name}.bin").is_file() for name in MODEL_FILES)
    for name, (check_bin, check_txt) in _CHECKS.items():
        path = model / f"{name}{'.bin' if binary else '.txt'}"
        if path.is_file() and binary:
            check_bin(_Binary(path))
        elif path.is_file():
            check_txt(path, path.read_text(errors="replace"))


@functools.cache
def _camera_models() -> dict[str, tuple[int, int]]:
    """COLMAP camera model name -> (id, number of parameters), from pycolmap."""
    import pycolmap

    return {m.name: (int(m.value), len(pycolmap.Camera.create_from_model_id(0, m, 1.0, 1, 1).params))
            for m in pycolmap.CameraModelId.__members__.values() if int(m.value) >= 0}


class _Binary:
    """A binary model file read front to back."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0
        if not self.data:
            raise SceneError(f"{path}: empty file")

    def read(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.at + size > len(self.data):
            raise SceneError(f"{self.path}: truncated in {what}")
        self.at += size
        return struct.unpack_from(fmt, self.data, self.at - size)

    def skip(self, size: int, what: str) -> None:
        self.at += size
        if self.at > len(self.data):
            raise SceneError(f"{self.path}: truncated in {what}")

    def count(self, fmt: str, least: int, what: str) -> int:
        """A count of records at least ``least`` bytes each, checked against the bytes left."""
        n = self.read(fmt, f"the count of {what}")[0]
        if n * least > len(self.data) - self.at:
            raise SceneError(f"{self.path}: truncated: declares {n} {what}, holds {len(self.data) - self.at} bytes")
        return n

    def end(self) -> None:
        if self.at != len(self.data):
            raise SceneError(f"{self.path}: {len(self.data) - self.at} bytes after the records it declares")


def _cameras_bin(f: _Binary) -> None:
    params = {i: n for i, n in _camera_models().values()}
    for i in range(f.count("<Q", 24, "cameras")):
        camera_id, model = f.read("<Ii16x", f"camera {i}")  # id, model, width, height
        if model not in params:
            raise SceneError(f"{f.path}: camera {camera_id} has unknown model id {model}")
        f.skip(8 * params[model], f"camera {camera_id}")
    f.end()


def _images_bin(f: _Binary) -> None:
    for i in range(f.count("<Q", 73, "images")):
        f.skip(64, f"image {i}")  # id, rotation, translation, camera id
        name_end = f.data.find(b"\0", f.at)
        if name_end < 0:
            raise SceneError(f"{f.path}: truncated in the name of image {i}")
        f.at = name_end + 1
        f.skip(24 * f.count("<Q", 24, f"points of image {i}"), f"image {i}")
    f.end()


def _points3d_bin(f: _Binary) -> None:
    n = f.count("<Q", 51, "points")
    data, at, size = f.data, f.at, len(f.data)
    track = struct.Struct("<43xQ").unpack_from  # id, xyz, rgb, error; then the track length
    for i in range(n):  # a tight loop: models hold millions of points
        if at + 51 > size:
            raise SceneError(f"{f.path}: truncated in point {i} of {n}")
        at += 51 + 8 * track(data, at)[0]
    f.at = at
    if at > size:
        raise SceneError(f"{f.path}: truncated in point {n - 1} of {n}")
    f.end()


def _rigs_bin(f: _Binary) -> None:
    for i in range(f.count("<Q", 8, "rigs")):
        for j in range(f.count("<4xI", 8, f"sensors of rig {i}")):
            if j == 0:
                f.skip(8, f"rig {i}")  # the reference sensor: type, id
            elif f.read("<8xB", f"rig {i}")[0]:  # another: type, id, has_pose
                f.skip(56, f"rig {i}")
    f.end()


def _frames_bin(f: _Binary) -> None:
    for i in range(f.count("<Q", 68, "frames")):
        f.skip(64, f"frame {i}")  # id, rig id, rig_from_world
        f.skip(16 * f.count("<I", 16, f"data ids of frame {i}"), f"frame {i}")
    f.end()


def _rows(path: Path, text: str, what: str) -> list[tuple[int, list[str]]]:
    """(line number, columns) of each data line, checked against the ``# Number of WHAT: N``
    that COLMAP writes (a file cut at a line's end reads as fewer records)."""
    rows = [(n, line.split()) for n, line in enumerate(text.splitlines(), 1)
            if line.strip() and not line.strip().startswith("#")]
    _check_declared(path, text, what, len(rows))
    return rows


def _check_declared(path: Path, text: str, what: str, held: int) -> None:
    declared = re.search(rf"^#\s*Number of {what}:\s*(\d+)", text, re.M)
    if declared and int(declared.group(1)) != held:
        raise SceneError(f"{path}: says 'Number of {what}: {declared.group(1)}' but holds {held} (truncated?)")


def _columns(path: Path, line: int, cols: list[str], need: int, what: str) -> None:
    if len(cols) != need:
        raise SceneError(f"{path}: line {line}: {len(cols)} columns, {what} needs {need}")


def _cameras_txt(path: Path, text: str) -> None:
    rows = _rows(path, text, "cameras")
    if not rows:
        raise SceneError(f"{path}: no cameras (empty or truncated file)")
    for line, cols in rows:
        if len(cols) < 4 or cols[1] not in _camera_models():
            raise SceneError(f"{path}: line {line}: not CAMERA_ID MODEL WIDTH HEIGHT PARAMS[] with a known MODEL")
        _columns(path, line, cols, 4 + _camera_models()[cols[1]][1], f"a {cols[1]} camera")


def _images_txt(path: Path, text: str) -> None:
    lines, images, i = text.splitlines(), 0, 0
    while i < len(lines):
        cols, i = lines[i].split(), i + 1
        if not cols or cols[0].startswith("#"):
            continue
        images += 1
        if len(cols) < 10:
            raise SceneError(f"{path}: line {i}: {len(cols)} columns, an image needs 10 "
                             "(IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME)")
        if i == len(lines):
            raise SceneError(f"{path}: truncated: no POINTS2D line after line {i}")
        if len(lines[i].split()) % 3:
            raise SceneError(f"{path}: line {i + 1}: {len(lines[i].split())} columns, POINTS2D needs "
                             "(X Y POINT3D_ID) triples")
        i += 1
    if not images:
        raise SceneError(f"{path}: no images (empty or truncated file)")
    _check_declared(path, text, "images", images)


def _points3d_txt(path: Path, text: str) -> None:
    for line, cols in _rows(path, text, "points"):
        if len(cols) < 8 or len(cols) % 2:
            raise SceneError(f"{path}: line {line}: {len(cols)} columns, a point needs 8 "
                             "(POINT3D_ID X Y Z R G B ERROR) and (IMAGE_ID POINT2D_IDX) pairs")


def _rigs_txt(path: Path, text: str) -> None:
    for line, cols in _rows(path, text, "rigs"):
        sensors = int(cols[1]) if len(cols) > 1 and cols[1].isdigit() else 0
        need = 2 + 2 * (sensors > 0)  # RIG_ID NUM_SENSORS [REF_SENSOR_TYPE REF_SENSOR_ID]
        for _ in range(sensors - 1):  # SENSOR_TYPE SENSOR_ID HAS_POSE [QW QX QY QZ TX TY TZ]
            need += 3
            if need > len(cols):
                break
            need += 7 * (cols[need - 1] == "1")
        _columns(path, line, cols, need, f"rig {cols[0] if cols else '?'}")


def _frames_txt(path: Path, text: str) -> None:
    for line, cols in _rows(path, text, "frames"):
        need = 10 + 3 * int(cols[9]) if len(cols) >= 10 and cols[9].isdigit() else 10
        _columns(path, line, cols, need, f"frame {cols[0] if cols else '?'}")


_CHECKS = {"rigs": (_rigs_bin, _rigs_txt), "cameras": (_cameras_bin, _cameras_txt),
           "frames": (_frames_bin, _frames_txt), "images": (_images_bin, _images_txt),
           "points3D": (_points3d_bin, _points3d_txt)}
