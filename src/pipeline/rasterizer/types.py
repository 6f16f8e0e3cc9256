"""Inputs and outputs of the surfel rasterizer, validated on construction.

Frames and units: ``means`` and ``quats`` live in the world frame (DTU: millimetres);
``world_to_cam`` maps world points to the OpenCV camera frame (x right, y down,
z forward); pixel ``(row i, col j)`` has its centre at image coordinates ``(x=j, y=i)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

FLOAT_DTYPES = (torch.float32, torch.float64)


def _finite(name: str, t: Tensor) -> None:
    # A finite sum proves every value finite (a NaN or an Inf makes the sum NaN or Inf) in
    # one pass without a mask: 0.1 ms instead of 1-2 ms for 200k surfels, every render.
    # Only a sum that is not finite (possibly an overflow of finite values) needs the mask.
    with torch.no_grad():
        if t.numel() and bool(torch.isfinite(t.sum())):
            return
        if not bool(torch.isfinite(t).all()):
            raise ValueError(f"{name} has non-finite values (NaN or Inf)")


@dataclass(frozen=True)
class Surfels:
    """A set of ``P`` 2D Gaussian surfels (all tensors on one device, one float dtype).

    Attributes:
        means: ``(P, 3)`` centres in the world frame.
        quats: ``(P, 4)`` world-frame orientations as ``(w, x, y, z)`` quaternions; they
            need not be unit length (they are normalised here) but must be non-zero. The
            rotation's first two columns are the tangent axes ``t_u, t_v``, the third the
            normal ``t_u x t_v``.
        scales: ``(P, 2)`` standard deviations along ``t_u, t_v`` in world units, > 0
            (already activated, e.g. ``exp`` of the optimised parameter).
        opacities: ``(P,)`` in ``[0, 1]`` (already activated).
        features: ``(P, C)`` colours or features of any channel count when ``sh_degree``
            is ``None``; else ``(P, K, 3)`` spherical-harmonic coefficients with
            ``K >= (sh_degree + 1)**2`` and ``sh_degree <= 3``.
        sh_degree: ``None`` for plain features, else the SH degree to evaluate.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    features: Tensor
    sh_degree: int | None = None

    def __post_init__(self) -> None:
        fields = {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "features": self.features,
        }
        for name, t in fields.items():
            if not isinstance(t, Tensor):
                raise ValueError(f"surfels.{name} must be a torch.Tensor, got {type(t).__name__}")
        if self.means.ndim != 2 or self.means.shape[1] != 3:
            raise ValueError(f"surfels.means must be (P, 3), got {tuple(self.means.shape)}")
        P = self.means.shape[0]
        expected = {"quats": (P, 4), "scales": (P, 2), "opacities": (P,)}
        for name, shape in expected.items():
            if tuple(fields[name].shape) != shape:
                raise ValueError(f"surfels.{name} must be {shape} for P={P}, got {tuple(fields[name].shape)}")
        dtype, device = self.means.dtype, self.means.device
        if dtype not in FLOAT_DTYPES:
            raise ValueError(f"surfels must be float32 or float64, got {dtype}")
        for name, t in fields.items():
            if t.dtype != dtype or t.device != device:
                raise ValueError(
                    f"surfels.{name} is {t.dtype} on {t.device}; all fields must be {dtype} on {device}"
                )
        if self.sh_degree is None:
            if self.features.ndim != 2 or self.features.shape[0] != P or self.features.shape[1] < 1:
                raise ValueError(f"surfels.features must be (P={P}, C>=1), got {tuple(self.features.shape)}")
        else:
            if not (isinstance(self.sh_degree, int) and 0 <= self.sh_degree <= 3):
                raise ValueError(f"sh_degree must be an int in 0..3, got {self.sh_degree!r}")
            need = (self.sh_degree + 1) ** 2
            f = self.features
            if f.ndim != 3 or f.shape[0] != P or f.shape[1] < need or f.shape[2] != 3:
                raise ValueError(
                    f"surfels.features must be SH coefficients (P={P}, K>={need}, 3) for sh_degree="
                    f"{self.sh_degree}, got {tuple(f.shape)}"
                )
        for name, t in fields.items():
            _finite(f"surfels.{name}", t)
        if not P:
            return
        with torch.no_grad():  # reductions rather than masks: one pass each, no allocation
            if bool(self.scales.min() <= 0):
                raise ValueError("surfels.scales must be > 0 (pass activated scales)")
            lo, hi = torch.aminmax(self.opacities)
            if bool(lo < 0) or bool(hi > 1):
                raise ValueError("surfels.opacities must lie in [0, 1] (pass activated opacities)")
            if bool(self.quats.norm(dim=1).min() == 0):
                raise ValueError("surfels.quats has a zero quaternion (no rotation)")

    @property
    def num_surfels(self) -> int:
        return int(self.means.shape[0])


@dataclass(frozen=True)
class Camera:
    """A pinhole camera. Not differentiable (its tensors are treated as constants).

    Attributes:
        K: ``(3, 3)`` intrinsics, last row ``(0, 0, 1)``, positive focal lengths; a skew
            ``K[0, 1]`` is allowed. Integer pixel-centre convention.
        world_to_cam: ``(4, 4)`` rigid world -> camera (OpenCV axes).
        width, height: image size in pixels.
        near, far: clipping depths (camera z, world units). Surfels whose centre lies
            outside ``[near, far]`` are culled; a ray–splat intersection with depth
            ``< near`` is skipped. ``near`` and ``far`` also define the distortion's
            normalised depth ``m = far / (far - near) * (1 - near / z)``.
    """

    K: Tensor
    world_to_cam: Tensor
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10

    def __post_init__(self) -> None:
        K = torch.as_tensor(np.asarray(self.K, dtype=np.float64) if not isinstance(self.K, Tensor) else self.K)
        w2c = self.world_to_cam
        w2c = torch.as_tensor(np.asarray(w2c, dtype=np.float64) if not isinstance(w2c, Tensor) else w2c)
        K = K.detach().to("cpu", torch.float64)
        w2c = w2c.detach().to("cpu", torch.float64)
        if K.shape != (3, 3):
            raise ValueError(f"camera.K must be 3x3, got {tuple(K.shape)}")
        if w2c.shape != (4, 4):
            raise ValueError(f"camera.world_to_cam must be 4x4, got {tuple(w2c.shape)}")
        _finite("camera.K", K)
        _finite("camera.world_to_cam", w2c)
        if not torch.equal(K[2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)):
            raise ValueError(f"camera.K last row must be (0, 0, 1), got {K[2].tolist()}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0:
            raise ValueError("camera.K must be upper triangular with positive focal lengths")
        R = w2c[:3, :3]
        if (R.T @ R - torch.eye(3, dtype=torch.float64)).abs().max() > 1e-5 or torch.det(R) < 0:
            raise ValueError("camera.world_to_cam[:3, :3] must be a rotation (orthonormal, det +1)")
        if not torch.equal(w2c[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)):
            raise ValueError("camera.world_to_cam last row must be (0, 0, 0, 1)")
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < 1:
                raise ValueError(f"camera.{name} must be a positive int, got {v!r}")
        if not (np.isfinite(self.near) and np.isfinite(self.far) and 0 < self.near < self.far):
            raise ValueError(f"camera needs 0 < near < far (finite), got near={self.near}, far={self.far}")
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "world_to_cam", w2c)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "near", float(self.near))
        object.__setattr__(self, "far", float(self.far))

    @property
    def cam_center(self) -> Tensor:
        """Camera centre in the world frame, ``-R^T t`` (float64)."""
        R, t = self.world_to_cam[:3, :3], self.world_to_cam[:3, 3]
        return -R.T @ t


@dataclass
class RenderOutput:
    """Per-pixel renders (``H x W``, image rows first) and per-surfel screen data.

    All per-pixel maps are differentiable w.r.t. every surfel parameter.

    Attributes:
        features: ``(H, W, C)`` ``sum_i w_i f_i`` with ``w_i = alpha_i T_i`` (no
            background; add ``bg * (1 - alpha)`` yourself).
        alpha: ``(H, W)`` accumulated opacity ``1 - prod_i (1 - alpha_i)``.
        depth_expected: ``(H, W)`` ``sum_i w_i z_i / (sum_i w_i + eps)``, ``z_i`` the camera
            z of the ray–splat intersection (world units); 0 where nothing is hit. It is
            positive wherever any surfel contributes, however faint ``alpha`` is there, so
            it is a depth map in the project's convention (``init.io.DepthMap``: 0 = no
            depth) only together with a validity mask such as ``alpha > 0.5``, which
            ``losses.gcf_loss`` requires.
        depth_median: ``(H, W)`` depth of the last surfel composited while the
            transmittance is still > 0.5; 0 where that never happens (no depth).
        normal_cam: ``(H, W, 3)`` ``sum_i w_i n_i`` in the camera frame, each ``n_i`` the
            unit surfel normal flipped to face the camera (not renormalised: divide by
            ``alpha`` for a mean direction).
        normal_world: ``(H, W, 3)`` the same blended normal rotated to the world frame.
        distortion: ``(H, W)`` 2DGS depth distortion ``sum_{i>j} w_i w_j (m_i - m_j)^2``
            with ``m = far/(far-near) (1 - near/z)``; the loss is its mean.
        radii: ``(P,)`` int32 screen radius in pixels of each surfel's support box
            (0 = culled or off-screen). For densification/pruning.
        means2d: ``(P, 2)`` projected centres in pixels. When autograd is on it is a
            leaf tensor with ``requires_grad``; after ``backward`` its ``.grad`` is the
            gradient w.r.t. a screen-space translation of each splat (pixels), the
            quantity 2DGS/gsplat densify on.
    """

    features: Tensor
    alpha: Tensor
    depth_expected: Tensor
    depth_median: Tensor
    normal_cam: Tensor
    normal_world: Tensor
    distortion: Tensor
    radii: Tensor
    means2d: Tensor
