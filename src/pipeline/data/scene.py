"""The scene model: posed images of one object, with units and frames explicit."""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline import geometry
from pipeline.errors import InputError


class SceneError(InputError):
    """Bad scene input. The message names the file and the problem."""


@dataclass
class Scene:
    """Posed views of one object.

    Attributes:
        name: scan name (``scan24``, ``synth_plate`` ...).
        images: ``(N, H, W, 3)`` float32 RGB in [0, 1].
        masks: ``(N, H, W)`` bool object masks, or ``None``.
        K: ``(N, 3, 3)`` intrinsics at this image size (integer pixel centres).
        world_to_cam: ``(N, 4, 4)`` rigid world(mm) -> camera transforms (OpenCV axes).
        norm_to_world: ``(4, 4)`` similarity mapping the normalised unit sphere to world mm.
        view_ids: index of each view in its source scan (DTU: 0..48).
        source: directory the scene was read from.
        scan_id: DTU scan number (synthetic scenes use ids >= 1000), if known.
    """

    name: str
    images: np.ndarray
    masks: np.ndarray | None
    K: np.ndarray
    world_to_cam: np.ndarray
    norm_to_world: np.ndarray
    view_ids: list[int]
    source: Path | None = None
    scan_id: int | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.view_ids)
        if self.images.ndim != 4 or self.images.shape[0] != n or self.images.shape[-1] != 3:
            raise SceneError(f"{self.name}: images must be (N={n}, H, W, 3), got {self.images.shape}")
        if self.K.shape != (n, 3, 3) or self.world_to_cam.shape != (n, 4, 4):
            raise SceneError(
                f"{self.name}: expected K (N,3,3) and world_to_cam (N,4,4) for N={n} views, "
                f"got {self.K.shape} and {self.world_to_cam.shape}"
            )
        if self.masks is not None and self.masks.shape != self.images.shape[:3]:
            raise SceneError(f"{self.name}: masks {self.masks.shape} do not match images {self.images.shape[:3]}")

    @property
    def num_views(self) -> int:
        return len(self.view_ids)

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def norm_scale_mm(self) -> float:
        """Radius of the normalised unit sphere in mm (``scale_mat[0, 0]``)."""
        return float(self.norm_to_world[0, 0])

    def camera_centers_world_mm(self) -> np.ndarray:
        """``(N, 3)`` camera centres in the world frame (mm)."""
        return np.stack([geometry.camera_center(T) for T in self.world_to_cam])

    def world_to_cam_normalised(self) -> np.ndarray:
        """``(N, 4, 4)`` rigid transforms from the normalised frame to a camera frame in
        normalised units (camera-frame lengths divided by :attr:`norm_scale_mm`)."""
        S = self.norm_to_world
        s = self.norm_scale_mm
        out = np.einsum("nij,jk->nik", self.world_to_cam, S)
        out[:, :3, :] /= s
        out[:, 3] = [0.0, 0.0, 0.0, 1.0]
        return out

    def fingerprint(self) -> str:
        """A short hash of the views, their pixels and cameras: outputs computed from a
        scene record it, so a later stage can refuse another scene's outputs."""
        h = hashlib.sha256()
        h.update(json.dumps([list(map(int, self.view_ids)), self.width, self.height]).encode())
        h.update(np.round(self.images * 255.0).astype(np.uint8).tobytes())
        for arr in (self.K, self.world_to_cam, self.norm_to_world):
            h.update(np.round(np.asarray(arr, np.float64), 6).tobytes())
        return h.hexdigest()[:16]

    def projections_world(self) -> np.ndarray:
        """``(N, 4, 4)`` DTU-style projections ``K [R | t]`` (world mm -> pixels)."""
        return np.stack([geometry.compose_projection(k, T) for k, T in zip(self.K, self.world_to_cam)])


def check_scene(scene: Scene, min_views: int = 1, needed_by: str = "this stage") -> None:
    """Reject a scene the stages cannot use: non-finite images or cameras, or fewer than
    ``min_views`` views (``needed_by`` names who needs them). The message names the scene
    folder."""
    where = scene.source or scene.name
    if not np.all(np.isfinite(scene.images)):
        raise SceneError(f"{where}: images have non-finite values")
    for name, arr in (("K", scene.K), ("world_to_cam", scene.world_to_cam), ("norm_to_world", scene.norm_to_world)):
        if not np.all(np.isfinite(arr)):
            raise SceneError(f"{where}: {name} has non-finite values")
    if scene.num_views < min_views:
        raise SceneError(f"{where}: {needed_by} needs at least {min_views} views, got {scene.num_views}")


def check_made_from(scene: Scene, folder: str | Path, info_name: str, stage: str) -> dict:
    """Refuse ``stage``'s output ``folder`` when its facts file ``info_name`` records another
    scene's fingerprint (:meth:`Scene.fingerprint`): outputs of another scene of the same
    size would otherwise be used without a word. A folder without that record (a cloud or
    priors a user made elsewhere) is taken as it is. Returns the facts (``{}`` without)."""
    path = Path(folder) / info_name
    if not path.is_file():
        return {}
    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise SceneError(f"{path}: cannot read ({exc})") from exc
    recorded = info.get("scene_fingerprint") if isinstance(info, dict) else None
    if recorded is not None and recorded != scene.fingerprint():
        raise SceneError(f"{path}: this {stage} output was computed from another scene "
                         f"({info.get('scene', '?')}) than {scene.source}; rerun `gcgs {stage}` for this scene")
    return info if isinstance(info, dict) else {}
