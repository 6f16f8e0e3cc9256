"""File formats of the priors stage (docs/priors.md).

* ``normals/{view:03d}.npz``: ``normal_cam`` float32 (H, W, 3), unit normals in the
  view's OpenCV camera frame facing the camera (0 where invalid); ``valid`` bool (H, W),
  Eq. 10's set M; ``view_id`` int64; ``backend`` str.
* ``features/{view:03d}.npz``: ``features`` float16/float32 (C, h, w); ``image_size``
  int64 (2,) = (H', W'), the image size the feature grid refers to (feature pixel centre
  j at image ``(j + 0.5) W'/w - 0.5``); ``view_id`` int64; ``backend`` str.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import atomic
from pipeline.errors import InputError
from pipeline.npz import read_npz


class PriorsFormatError(InputError):
    """A priors file that cannot be read; the message names the file."""


@dataclass
class NormalPrior:
    view_id: int
    normal_cam: np.ndarray  # (H, W, 3) float32, camera frame, facing the camera
    valid: np.ndarray  # (H, W) bool
    backend: str


@dataclass
class FeaturePrior:
    view_id: int
    features: np.ndarray  # (C, h, w) float32
    image_size: tuple[int, int]  # (H', W') the grid refers to
    backend: str


def normals_path(out_dir: str | Path, view_id: int) -> Path:
    return Path(out_dir) / "normals" / f"{int(view_id):03d}.npz"


def features_path(out_dir: str | Path, view_id: int) -> Path:
    return Path(out_dir) / "features" / f"{int(view_id):03d}.npz"


def _atomic_savez(path: Path, compressed: bool, **arrays) -> Path:
    with atomic.atomic_file(path, suffix=".npz") as tmp:
        (np.savez_compressed if compressed else np.savez)(tmp, **arrays)
    return path


def write_normals(path: str | Path, p: NormalPrior) -> Path:
    valid = np.asarray(p.valid, bool)
    n = np.where(valid[..., None], p.normal_cam, 0.0).astype(np.float32)
    return _atomic_savez(Path(path), True, normal_cam=n, valid=valid, view_id=np.int64(p.view_id),
                         backend=np.str_(p.backend))


def write_features(path: str | Path, p: FeaturePrior, dtype: str = "float16") -> Path:
    f = p.features.astype(dtype)
    if not np.all(np.isfinite(f)):
        raise PriorsFormatError(f"{path}: features of view {p.view_id} overflow {dtype} (max |f| = "
                                f"{np.abs(p.features).max():.3g}); set priors.feature_dtype: float32")
    # Feature maps are dense noise-like data: compression gains little and costs seconds.
    return _atomic_savez(Path(path), False, features=f,
                         image_size=np.asarray(p.image_size, np.int64), view_id=np.int64(p.view_id),
                         backend=np.str_(p.backend))


def read_normals(path: str | Path) -> NormalPrior:
    path = Path(path)
    d = read_npz(path, ("normal_cam", "valid", "view_id", "backend"), PriorsFormatError, "priors")
    n, valid = d["normal_cam"], d["valid"]
    if n.ndim != 3 or n.shape[2] != 3 or valid.shape != n.shape[:2]:
        raise PriorsFormatError(f"{path}: normal_cam {n.shape} must be (H, W, 3) and valid {valid.shape} (H, W)")
    if not np.all(np.isfinite(n)):
        raise PriorsFormatError(f"{path}: non-finite normals")
    return NormalPrior(int(d["view_id"]), n.astype(np.float32), valid.astype(bool), str(d["backend"]))


def read_features(path: str | Path) -> FeaturePrior:
    path = Path(path)
    d = read_npz(path, ("features", "image_size", "view_id", "backend"), PriorsFormatError, "priors")
    f, size = d["features"], d["image_size"]
    if f.ndim != 3 or size.shape != (2,):
        raise PriorsFormatError(f"{path}: features {f.shape} must be (C, h, w) and image_size (2,)")
    if not np.all(np.isfinite(f)):
        raise PriorsFormatError(f"{path}: non-finite features")
    return FeaturePrior(int(d["view_id"]), f.astype(np.float32), (int(size[0]), int(size[1])), str(d["backend"]))
