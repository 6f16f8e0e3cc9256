"""A capture as ``gcgs prepare`` reads it, whatever its folder layout (DTU NeuS/IDR, COLMAP,
nerfstudio): the cameras in the project's conventions, the image and mask files by view
id, and how to read them as the undistorted pinhole images the cameras are for.

Conventions (docs/inputs.md): cameras are OpenCV world-to-camera in the input's own world
frame and units; intrinsics use integer pixel centres (COLMAP's and nerfstudio's +0.5 is
removed by the readers); ``norm_to_world`` maps the unit sphere to the world (from the
input's file for DTU, else derived by :func:`sphere_from_points` or
:func:`sphere_from_cameras`).
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipeline.data import dtu
from pipeline.data.scene import SceneError


@dataclass
class Undistort:
    """A view's lens distortion in OpenCV's model (``dist`` = k1, k2, p1, p2[, k3]) for the
    pinhole ``K`` (integer pixel centres) the image is remapped to, at the same size."""

    K: np.ndarray
    dist: np.ndarray

    def maps(self, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        return cv2.initUndistortRectifyMap(self.K, self.dist, None, self.K, size, cv2.CV_32FC1)


@dataclass
class Capture:
    """Posed views of one object, read from a source folder.

    ``cameras`` are for the images as :meth:`read_image` returns them (undistorted, at
    ``size``); ``masks`` is ``None`` when the source has none, else has one file per view.
    """

    layout: str  # "dtu", "colmap", "nerfstudio"
    root: Path
    cameras: dtu.DTUCameras
    images: dict[int, Path]
    masks: dict[int, Path] | None
    size: tuple[int, int]  # (width, height) every image must have
    image_dir: Path  # named in messages about the images
    mask_dir: Path | None = None
    undistort: dict[int, Undistort] = field(default_factory=dict)
    notes: dict = field(default_factory=dict)  # written into scene.json (how scale_mat was made ...)

    def _check_size(self, path: Path, shape: tuple[int, ...], what: str) -> None:
        h, w = shape[:2]
        if (w, h) != self.size:
            raise SceneError(f"{path}: {what} is {w}x{h} but its camera is for {self.size[0]}x{self.size[1]}")

    def _remap(self, v: int, arr: np.ndarray) -> np.ndarray:
        u = self.undistort.get(v)
        if u is None:
            return arr
        mx, my = u.maps(self.size)
        return cv2.remap(arr, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def read_image(self, v: int) -> np.ndarray:
        """View ``v``'s RGB float32 image, undistorted when its lens has distortion."""
        path = self.images[v]
        img = dtu.read_image(path)
        self._check_size(path, img.shape, "the image")
        return self._remap(v, img)

    def read_mask(self, v: int) -> np.ndarray:
        """View ``v``'s bool mask, undistorted like its image."""
        assert self.masks is not None
        path = self.masks[v]
        m = dtu.read_mask(path)
        self._check_size(path, m.shape, "the mask")
        if v in self.undistort:
            m = self._remap(v, m.astype(np.float32)) > 0.5
        return m


def common_size(sizes: dict[str, tuple[int, int]], where: Path) -> tuple[int, int]:
    """The one image size of a capture's cameras (``sizes``: name -> (w, h)); another size
    is an error naming the camera (training needs one size for every view)."""
    common = Counter(sizes.values()).most_common(1)[0][0]
    for name, size in sizes.items():
        if size != common:
            raise SceneError(f"{where}: {name} is {size[0]}x{size[1]} but the other views are {common[0]}x{common[1]}; "
                             "every view must have the same size")
    return common


def sphere_matrix(centre: np.ndarray, radius: float) -> np.ndarray:
    """The ``scale_mat`` of a sphere: ``x_world = radius * x_norm + centre``."""
    S = np.eye(4)
    S[:3, :3] *= float(radius)
    S[:3, 3] = centre
    return S


def sphere_from_points(points: np.ndarray, quantile: float = 0.95, margin: float = 1.1) -> tuple[np.ndarray, float]:
    """A sphere around the robust extent of sparse points: centred at their per-axis
    median, its radius ``margin`` times the ``quantile`` of their distances to it (so a few
    far outliers of structure-from-motion do not blow it up)."""
    pts = np.asarray(points, np.float64)
    centre = np.median(pts, axis=0)
    radius = float(np.quantile(np.linalg.norm(pts - centre, axis=1), quantile)) * margin
    return centre, radius


def sphere_from_cameras(K: dict[int, np.ndarray], world_to_cam: dict[int, np.ndarray],
                        size: tuple[int, int], margin: float = 1.1) -> tuple[np.ndarray, float]:
    """A sphere where the cameras look: centred at the point nearest (least squares) to
    every optical axis, its radius ``margin`` times the radius that holds each view's whole
    frame (the cone to its farthest image corner) at that point's distance, median over
    the views. An object the views frame fits inside; on DTU's rig this is 0.97x the
    ``scale_mat`` DTU ships (docs/inputs.md). ``size`` is (width, height) in the pixels of
    ``K`` (integer pixel centres). Cameras looking in parallel, or whose axes meet behind
    one of them, have no such point: an error."""
    A, b, cams = np.zeros((3, 3)), np.zeros(3), []
    for v in sorted(K):
        T = world_to_cam[v]
        c = -T[:3, :3].T @ T[:3, 3]
        d = T[2, :3]  # the optical axis in the world: the camera's z row
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
        cams.append((v, c))
    if len(cams) < 2 or np.linalg.cond(A) > 1e8:
        raise SceneError("the cameras' optical axes do not meet (parallel or a single view): cannot place the "
                         "object's sphere; give sparse points (COLMAP points3D) or a DTU cameras_sphere.npz")
    centre = np.linalg.solve(A, b)
    w, h = size
    corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
    radii = []
    for v, c in cams:
        T, k = world_to_cam[v], K[v]
        depth = float((T[:3, :3] @ centre + T[:3, 3])[2])
        if depth <= 0:
            raise SceneError(f"the cameras' optical axes do not meet in front of the cameras (behind view {v}): "
                             "cannot place the object's sphere; give sparse points (COLMAP points3D) or a DTU "
                             "cameras_sphere.npz")
        rays = np.column_stack([(corners[:, 0] - k[0, 2]) / k[0, 0], (corners[:, 1] - k[1, 2]) / k[1, 1]])
        half = np.arctan(np.linalg.norm(rays, axis=1).max())  # the widest corner's angle to the axis
        radii.append(np.linalg.norm(centre - c) * np.sin(half))
    return centre, margin * float(np.median(radii))
