"""Training views: images, masks, cameras (normalised frame) and priors of each input
view, at each training resolution of the schedule (built once, on first use)."""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from pipeline import geometry
from pipeline.data.scene import Scene, SceneError
from pipeline.init.io import read_depth
from pipeline.priors.io import features_path, normals_path, read_features, read_normals
from pipeline.rasterizer import Camera


@dataclass
class ViewData:
    """One input view at one resolution. Tensors are float32 (masks bool)."""

    view_id: int
    image: torch.Tensor  # (3, h, w) in [0, 1]
    mask: torch.Tensor | None  # (h, w) bool, object pixels
    K: torch.Tensor  # (3, 3) intrinsics at (h, w), integer pixel centres
    world_to_cam: torch.Tensor  # (4, 4) normalised frame -> camera frame in normalised units
    camera: Camera
    normal_prior: torch.Tensor | None  # (3, h, w) camera frame, facing the camera
    normal_valid: torch.Tensor | None  # (h, w) bool
    features: torch.Tensor | None  # (C, h', w'), resolution independent
    feature_image_size: tuple[float, float] | None  # the (H, W) of this resolution the features refer to
    mvs_depth: torch.Tensor | None = None  # (h, w) camera z of the init's MVS depth, normalised units; 0 = none

    @property
    def size(self) -> tuple[int, int]:
        return int(self.image.shape[1]), int(self.image.shape[2])


def _area(img: np.ndarray, w: int, h: int) -> np.ndarray:
    return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA) if img.shape[:2] != (h, w) else img


MAX_REL_DEPTH_SPREAD = 0.005  # a coarse pixel whose footprint's depths spread more (an edge) gets none


def _depth_at(depth: np.ndarray, w: int, h: int) -> np.ndarray:
    """``depth`` (0 = none) area-averaged to ``w x h``; a coarse pixel has depth only where
    its whole footprint had, with a relative spread below ``MAX_REL_DEPTH_SPREAD`` (no
    averaging across depth edges)."""
    if depth.shape == (h, w):
        return depth
    valid = (depth > 0).astype(np.float64)
    mean = _area(depth, w, h)
    spread = np.sqrt(np.maximum(_area(depth * depth, w, h) - mean * mean, 0.0))
    ok = (_area(valid, w, h) > 1 - 1e-6) & (spread < MAX_REL_DEPTH_SPREAD * np.maximum(mean, 1e-12))
    return np.where(ok, mean, 0.0)


def crop_window(size: tuple[int, int], fraction: float, mask: torch.Tensor | None,
                generator: torch.Generator) -> tuple[int, int, int, int]:
    """A training window ``(x0, y0, w, h)`` (whole pixels) of ``fraction`` x the sides of a
    view of ``size`` ``(h, w)``: centred on a random mask pixel (on a random pixel without a
    mask, or with an empty one), then moved inside the image."""
    H, W = size
    w, h = max(1, round(fraction * W)), max(1, round(fraction * H))
    if mask is not None and bool(mask.any()):
        ys, xs = torch.nonzero(mask, as_tuple=True)
        k = int(torch.randint(len(xs), (1,), generator=generator))
        cx, cy = int(xs[k]), int(ys[k])
    else:
        cx, cy = int(torch.randint(W, (1,), generator=generator)), int(torch.randint(H, (1,), generator=generator))
    x0 = min(max(cx - w // 2, 0), W - w)
    y0 = min(max(cy - h // 2, 0), H - h)
    return x0, y0, w, h


def crop_view(v: ViewData, x0: int, y0: int, w: int, h: int) -> ViewData:
    """``v`` cut to the window ``[x0, x0 + w) x [y0, y0 + h)``: images, mask and priors
    sliced, the principal point moved by ``(x0, y0)`` (pixel ``(x0, y0)`` becomes ``(0, 0)``,
    integer pixel centres), so rendering the crop gives exactly that window of the whole
    view's render. Features (L_gcf) are not cut: a cropped view has none."""
    H, W = v.size
    if not (0 <= x0 and 0 <= y0 and w >= 1 and h >= 1 and x0 + w <= W and y0 + h <= H):
        raise ValueError(f"crop_view: window x0={x0}, y0={y0}, {w}x{h} is not inside the {W}x{H} view")
    cam = v.camera
    K = cam.K.clone()  # float64: the shift is exact
    K[0, 2] -= x0
    K[1, 2] -= y0
    ys, xs = slice(y0, y0 + h), slice(x0, x0 + w)
    return replace(
        v,
        image=v.image[:, ys, xs],
        mask=None if v.mask is None else v.mask[ys, xs],
        K=K.float(),
        camera=Camera(K, cam.world_to_cam, w, h, near=cam.near, far=cam.far),
        normal_prior=None if v.normal_prior is None else v.normal_prior[:, ys, xs],
        normal_valid=None if v.normal_valid is None else v.normal_valid[ys, xs],
        features=None,
        feature_image_size=None,
        mvs_depth=None if v.mvs_depth is None else v.mvs_depth[ys, xs],
    )


class TrainViews:
    """The input views of a scene with their priors; :meth:`at` gives a view at a
    downscale factor (area-averaged images, intrinsics rescaled with the integer pixel
    centre convention, normals averaged and renormalised, a pixel valid only where its
    whole footprint was)."""

    def __init__(self, scene: Scene, priors_dir: str | Path | None, use_masks: bool, want_normals: bool,
                 want_features: bool, near: float, far: float, mvs_depth_dir: str | Path | None = None):
        self.scene = scene
        self.use_masks = use_masks
        self.near, self.far = near, far
        self.w2c_norm = scene.world_to_cam_normalised()
        self.normals: list = [None] * scene.num_views
        self.features: list = [None] * scene.num_views
        for i, v in enumerate(scene.view_ids):
            if want_normals:
                p = normals_path(priors_dir, v)
                if not p.is_file():
                    raise SceneError(f"{p}: missing normal prior of view {v} (run the priors stage with loss.lambda_nor > 0)")
                prior = read_normals(p)
                if prior.normal_cam.shape[:2] != (scene.height, scene.width):
                    raise SceneError(f"{p}: normal map is {prior.normal_cam.shape[1]}x{prior.normal_cam.shape[0]}, "
                                     f"scene is {scene.width}x{scene.height} (stale priors?)")
                self.normals[i] = prior
            if want_features:
                p = features_path(priors_dir, v)
                if not p.is_file():
                    raise SceneError(f"{p}: missing feature map of view {v} (run the priors stage with loss.lambda_gcf > 0)")
                self.features[i] = read_features(p)
        # Full-resolution grey images (ITU-R 601 luma) for the multi-view NCC term.
        self.grey_full = [torch.from_numpy(np.ascontiguousarray(img @ np.array([0.299, 0.587, 0.114]))).float()
                          for img in scene.images]
        self.mvs_depth: list = [None] * scene.num_views
        if mvs_depth_dir is not None:
            for i, v in enumerate(scene.view_ids):
                p = Path(mvs_depth_dir) / f"{v:03d}.npz"
                if not p.is_file():
                    raise SceneError(f"{p}: missing MVS depth of view {v} (loss.lambda_mvs > 0 needs the mvs init's depth maps)")
                dm = read_depth(p)
                if dm.depth_mm.shape != (scene.height, scene.width):
                    raise SceneError(f"{p}: depth map is {dm.depth_mm.shape[1]}x{dm.depth_mm.shape[0]}, "
                                     f"scene is {scene.width}x{scene.height} (stale init?)")
                self.mvs_depth[i] = dm.depth_mm.astype(np.float64) / scene.norm_scale_mm
        self._cache: dict[tuple[int, int], ViewData] = {}

    @property
    def num_views(self) -> int:
        return self.scene.num_views

    def training_masks(self) -> list[np.ndarray] | None:
        """The masks the training uses, full resolution ``(H, W)`` bool per view; None
        when it uses none."""
        if not self.use_masks or self.scene.masks is None:
            return None
        return [np.asarray(m, bool) for m in self.scene.masks]

    def at(self, index: int, factor: int) -> ViewData:
        key = (index, factor)
        if key not in self._cache:
            self._cache[key] = self._build(index, factor)
        return self._cache[key]

    def _build(self, i: int, factor: int) -> ViewData:
        s = self.scene
        H, W = s.height, s.width
        h, w = max(1, round(H / factor)), max(1, round(W / factor))
        K = geometry.scale_intrinsics(s.K[i], w / W, h / H)
        image = _area(s.images[i], w, h)
        mask = None
        if self.use_masks and s.masks is not None:
            mask = torch.from_numpy(_area(s.masks[i].astype(np.float32), w, h) > 0.5)
        n_prior = n_valid = None
        if self.normals[i] is not None:
            pr = self.normals[i]
            valid = pr.valid.astype(np.float32)
            n = _area(pr.normal_cam * valid[..., None], w, h)
            v = _area(valid, w, h)
            norm = np.linalg.norm(n, axis=2, keepdims=True)
            n_valid = torch.from_numpy((v > 1 - 1e-6) & (norm[..., 0] > 1e-6))
            n_prior = torch.from_numpy(np.where(norm > 1e-6, n / np.maximum(norm, 1e-12), 0.0).transpose(2, 0, 1).copy()).float()
        feats = size = None
        if self.features[i] is not None:
            fp = self.features[i]
            feats = torch.from_numpy(fp.features)
            size = (fp.image_size[0] * h / H, fp.image_size[1] * w / W)
        mvs = None
        if self.mvs_depth[i] is not None:
            mvs = torch.from_numpy(_depth_at(self.mvs_depth[i], w, h)).float()
        w2c = self.w2c_norm[i]
        return ViewData(
            view_id=s.view_ids[i],
            image=torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))).float(),
            mask=mask,
            K=torch.from_numpy(K).float(),
            world_to_cam=torch.from_numpy(w2c).float(),
            camera=Camera(K, w2c, w, h, near=self.near, far=self.far),
            normal_prior=n_prior,
            normal_valid=n_valid,
            features=feats,
            feature_image_size=size,
            mvs_depth=mvs,
        )
