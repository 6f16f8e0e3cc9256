"""File formats of the init stage (documented in ``docs/init.md``).

* ``points.ply``: binary little-endian PLY; per vertex ``x y z`` (float32, world mm),
  ``nx ny nz`` (float32, unit normals), ``red green blue`` (uint8) and ``confidence``
  (float32 in [0, 1]). Written by hand so that the custom property is kept exactly.
* ``depth/{view:03d}.npz``: one per input view (``view`` = DTU view id):
  ``depth_mm`` float32 (H, W) camera-frame z in mm (0 = no depth), ``confidence``
  float32 (H, W) in [0, 1] (0 where invalid), ``valid`` bool (H, W), ``K`` float64 (3, 3)
  at this (H, W) with integer pixel centres, ``world_to_cam`` float64 (4, 4) world mm ->
  camera, ``view_id`` int64 scalar.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import atomic, ply
from pipeline.data.scene import Scene
from pipeline.errors import InputError
from pipeline.npz import read_npz


class InitFormatError(InputError):
    """A points.ply or depth file that cannot be read; the message names the file."""


@dataclass
class PointCloud:
    """A coloured, oriented point cloud in the world frame (mm)."""

    points_mm: np.ndarray  # (N, 3) float, world frame, mm
    colors: np.ndarray  # (N, 3) float in [0, 1]
    normals: np.ndarray  # (N, 3) unit vectors, world frame
    confidence: np.ndarray  # (N,) float in [0, 1]

    def __post_init__(self) -> None:
        n = len(self.points_mm)
        for name, arr, shape in (
            ("points_mm", self.points_mm, (n, 3)),
            ("colors", self.colors, (n, 3)),
            ("normals", self.normals, (n, 3)),
            ("confidence", self.confidence, (n,)),
        ):
            if arr.shape != shape:
                raise ValueError(f"PointCloud.{name} must have shape {shape}, got {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"PointCloud.{name} has non-finite values")

    def __len__(self) -> int:
        return len(self.points_mm)


_PLY_DTYPE = np.dtype(
    [
        ("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
        ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
        ("red", "u1"), ("green", "u1"), ("blue", "u1"),
        ("confidence", "<f4"),
    ]
)


def write_ply(path: str | Path, cloud: PointCloud) -> Path:
    """Write ``cloud`` as binary PLY (atomically: temp file in the same dir, then rename)."""
    rgb = np.clip(np.round(cloud.colors * 255.0), 0, 255).astype(np.uint8)
    columns = {name: cloud.points_mm[:, i] for i, name in enumerate("xyz")}
    columns.update({f"n{name}": cloud.normals[:, i] for i, name in enumerate("xyz")})
    columns.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2], confidence=cloud.confidence)
    return ply.write(path, {name: np.asarray(columns[name], _PLY_DTYPE[name]) for name in _PLY_DTYPE.names},
                     comments=("gcgs init point cloud: world frame, millimetres",))


def read_ply(path: str | Path) -> PointCloud:
    """Read a PLY written by :func:`write_ply`."""
    path = Path(path)
    if not path.is_file():
        raise InitFormatError(f"{path}: file not found")
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise InitFormatError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise InitFormatError(f"{path}: expected binary_little_endian PLY")
    try:
        n = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    except (StopIteration, IndexError, ValueError):
        raise InitFormatError(f"{path}: no 'element vertex N' line") from None
    props = [line.split()[-1] for line in header if line.startswith("property")]
    if props != list(_PLY_DTYPE.names):
        raise InitFormatError(f"{path}: vertex properties {props} differ from {list(_PLY_DTYPE.names)}")
    ply.check(raw, path, InitFormatError)
    body = raw[end + len(b"end_header\n"):]
    if len(body) != n * _PLY_DTYPE.itemsize:
        raise InitFormatError(f"{path}: {len(body)} bytes of vertex data, write_ply's types need "
                              f"{n * _PLY_DTYPE.itemsize} (other property types?)")
    rec = np.frombuffer(body, dtype=_PLY_DTYPE)
    try:
        return PointCloud(
            points_mm=np.stack([rec["x"], rec["y"], rec["z"]], 1).astype(np.float64),
            colors=np.stack([rec["red"], rec["green"], rec["blue"]], 1).astype(np.float32) / 255.0,
            normals=np.stack([rec["nx"], rec["ny"], rec["nz"]], 1).astype(np.float32),
            confidence=rec["confidence"].astype(np.float32),
        )
    except ValueError as exc:
        raise InitFormatError(f"{path}: {exc}") from exc


@dataclass
class DepthMap:
    """One view's depth in its own camera frame (mm), with confidence and validity.

    "No depth" has one encoding in the whole project: a depth map is camera-frame z in
    mm, finite everywhere, **0 where there is no depth**; never NaN or inf. Where a bool
    validity mask travels with it (here ``valid``), it marks exactly the pixels with
    depth > 0. A depth that is positive without being a surface point (a rendered
    expected depth where alpha is faint) needs such a mask to say which pixels count:
    :func:`pipeline.losses.gcf_loss` takes it as a required argument.
    """

    view_id: int
    depth_mm: np.ndarray  # (H, W) float32 camera z, mm; 0 = no depth
    confidence: np.ndarray  # (H, W) float32 in [0, 1]; 0 where there is no depth
    valid: np.ndarray  # (H, W) bool, == (depth_mm > 0)
    K: np.ndarray  # (3, 3) at (H, W)
    world_to_cam: np.ndarray  # (4, 4) world mm -> camera

    def __post_init__(self) -> None:
        if self.depth_mm.shape != self.valid.shape:
            raise ValueError(f"DepthMap {self.view_id}: depth {self.depth_mm.shape} and valid {self.valid.shape} differ")
        if not np.all(np.isfinite(self.depth_mm)) or np.any(self.depth_mm < 0):
            raise ValueError(f"DepthMap {self.view_id}: depth must be finite and >= 0 (0 = no depth)")
        if not np.array_equal(self.valid, self.depth_mm > 0):
            raise ValueError(f"DepthMap {self.view_id}: valid must be exactly the pixels with depth > 0")


DEPTH_KEYS = ("depth_mm", "confidence", "valid", "K", "world_to_cam", "view_id")


def depth_path(out_dir: str | Path, view_id: int) -> Path:
    return Path(out_dir) / "depth" / f"{int(view_id):03d}.npz"


def write_depth(path: str | Path, d: DepthMap) -> Path:
    """Write one depth map (atomically); confidence is zeroed where there is no depth."""
    path = Path(path)
    valid = np.asarray(d.valid, dtype=bool)
    depth = np.asarray(d.depth_mm, np.float32)
    conf = np.where(valid, d.confidence, 0.0).astype(np.float32)
    with atomic.atomic_file(path, suffix=".npz") as tmp:
        np.savez_compressed(
            tmp, depth_mm=depth, confidence=conf, valid=valid,
            K=np.asarray(d.K, np.float64), world_to_cam=np.asarray(d.world_to_cam, np.float64),
            view_id=np.int64(d.view_id),
        )
    return path


def read_depth(path: str | Path) -> DepthMap:
    """Read and check a depth file; errors name the file and the problem."""
    path = Path(path)
    data = read_npz(path, DEPTH_KEYS, InitFormatError, "depth")
    depth, conf, valid = data["depth_mm"], data["confidence"], data["valid"]
    if depth.ndim != 2 or conf.shape != depth.shape or valid.shape != depth.shape:
        raise InitFormatError(f"{path}: depth_mm {depth.shape}, confidence {conf.shape} and valid {valid.shape} must be equal (H, W)")
    if data["K"].shape != (3, 3) or data["world_to_cam"].shape != (4, 4):
        raise InitFormatError(f"{path}: K must be 3x3 and world_to_cam 4x4")
    if not np.all(np.isfinite(depth)) or not np.all(np.isfinite(conf)):
        raise InitFormatError(f"{path}: non-finite depth or confidence")
    if not np.array_equal(valid.astype(bool), depth > 0):
        raise InitFormatError(f"{path}: valid must be exactly the pixels with depth > 0 (0 = no depth)")
    return DepthMap(
        view_id=int(data["view_id"]), depth_mm=depth.astype(np.float32), confidence=conf.astype(np.float32),
        valid=valid.astype(bool), K=data["K"].astype(np.float64), world_to_cam=data["world_to_cam"].astype(np.float64),
    )


def load_init_depths(init_dir: str | Path, scene: Scene, needed_by: str) -> list[DepthMap]:
    """The init stage's depth maps of every view of ``scene``, checked against its size and
    cameras; ``needed_by`` says in the messages what needs them."""
    out = []
    for v, K, T in zip(scene.view_ids, scene.K, scene.world_to_cam):
        path = depth_path(init_dir, v)
        if not path.is_file():
            raise InitFormatError(f"{path}: missing depth map for view {v} ({needed_by} needs the depth maps of "
                                  "a depth-based init backend, mvs or mast3r)")
        d = read_depth(path)
        if d.depth_mm.shape != (scene.height, scene.width):
            raise InitFormatError(f"{path}: depth map is {d.depth_mm.shape[1]}x{d.depth_mm.shape[0]}, "
                                  f"scene {scene.source} is {scene.width}x{scene.height}")
        if not (np.allclose(d.K, K, rtol=1e-6, atol=1e-6) and np.allclose(d.world_to_cam, T, rtol=1e-6, atol=1e-6)):
            raise InitFormatError(f"{path}: camera differs from view {v} of {scene.source} (stale init output?)")
        if not d.valid.any():
            raise InitFormatError(f"{path}: no valid depth pixel")
        out.append(d)
    return out


def stacked_depths_mm(maps: list[DepthMap]) -> np.ndarray:
    """``(N, H, W)`` camera z in mm of ``maps``, 0 where a map has no valid depth (what TSDF
    fusion and the mesh's init-depth merge read)."""
    return np.stack([np.where(m.valid, m.depth_mm, 0.0) for m in maps])


@dataclass
class InitResult:
    """What a backend produces: the cloud, per-view depth maps (depth backends) and
    facts for ``init.json``."""

    cloud: PointCloud
    depths: list[DepthMap] | None
    info: dict
