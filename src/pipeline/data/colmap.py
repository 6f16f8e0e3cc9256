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
    try:
        rec = pycolmap.Reconstruction(str(model))
    except (ValueError, RuntimeError) as exc:  # pycolmap reports a bad file as ValueError
        raise SceneError(f"{model}: cannot read the COLMAP model ({exc})") from exc

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
