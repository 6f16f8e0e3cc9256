"""Camera geometry shared by every stage.

Conventions (used everywhere in this package):

* Cameras follow OpenCV: x right, y down, z forward; ``world_to_cam`` is a 4x4 rigid
  transform taking world points (DTU world frame, millimetres) to the camera frame.
* Pixel centres sit at integer coordinates: pixel ``(row i, col j)`` covers
  ``[j - 0.5, j + 0.5) x [i - 0.5, i + 0.5)`` in image coordinates. Hence resizing an
  image by a factor ``f`` maps a coordinate ``x`` to ``f * (x + 0.5) - 0.5``.
* ``norm_to_world`` (DTU ``scale_mat``) maps the normalised unit-sphere frame to the
  world frame in mm: ``x_world = S @ x_norm``.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg

from pipeline.errors import InputError


class CameraError(InputError):
    """A camera matrix that cannot be used (non-finite, singular, not a projection)."""


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection ``P = K [R | t]`` into intrinsics and world-to-camera.

    Uses an RQ decomposition of the left 3x3 block. ``K`` is upper triangular with a
    positive diagonal and ``K[2, 2] = 1`` (the small DTU skew ``K[0, 1]`` is kept);
    ``R`` is a proper rotation. Returns ``(K (3x3), world_to_cam (4x4))``.
    """
    P = np.asarray(P, dtype=np.float64)
    if P.shape == (4, 4):
        P = P[:3]
    if P.shape != (3, 4):
        raise CameraError(f"projection must be 3x4 or 4x4, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise CameraError("projection matrix has non-finite entries")
    M = P[:, :3]
    if abs(np.linalg.det(M)) < 1e-12 * max(1.0, np.abs(M).max()) ** 3:
        raise CameraError("projection matrix is singular (its left 3x3 block has no inverse)")
    K, R = scipy.linalg.rq(M)
    # Make the diagonal of K positive: K R = (K D)(D R) with D = diag(sign).
    D = np.diag(np.sign(np.diag(K)))
    K, R = K @ D, D @ R
    t = np.linalg.solve(K, P[:, 3])
    if np.linalg.det(R) < 0:  # P was given up to a negative scale
        R, t = -R, -t
    K = K / K[2, 2]
    world_to_cam = np.eye(4)
    world_to_cam[:3, :3] = R
    world_to_cam[:3, 3] = t
    return K, world_to_cam


def compose_projection(K: np.ndarray, world_to_cam: np.ndarray) -> np.ndarray:
    """4x4 padding of ``K [R | t]`` (the DTU ``world_mat`` form). The product is summed in a
    fixed order rather than by BLAS, whose kernels (and last bits) differ between CPUs: the
    same cameras give the same file bytes on any machine."""
    P = np.eye(4)
    P[:3, :4] = (np.asarray(K, np.float64)[:, :, None] * np.asarray(world_to_cam, np.float64)[None, :3, :4]).sum(axis=1)
    return P


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics after resizing an image by ``(sx, sy)`` (new size / old size).

    With integer pixel centres, ``x' = sx (x + 0.5) - 0.5``.
    """
    S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
    return S @ np.asarray(K, dtype=np.float64)


def project(K: np.ndarray, world_to_cam: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project ``(N, 3)`` world points; returns ``(pixels (N, 2), depth (N,))``.

    Depth is the camera-frame z. Pixels of points with ``z <= 0`` are not meaningful.
    """
    points = np.asarray(points, dtype=np.float64)
    cam = points @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
    z = cam[:, 2]
    uvw = cam @ np.asarray(K, dtype=np.float64).T
    with np.errstate(divide="ignore", invalid="ignore"):
        px = uvw[:, :2] / uvw[:, 2:3]
    return px, z


def pixel_rays(K: np.ndarray, xs: np.ndarray | None = None, ys: np.ndarray | None = None,
               shape: tuple[int, int] | None = None) -> np.ndarray:
    """Camera-frame rays with z = 1 through image points, so a ray times a camera depth z
    is the camera-frame point: ``K^-1 [x, y, 1]``, shape ``xs.shape + (3,)``.

    Give the points as ``xs``, ``ys`` (same shapes; integer pixel centres), or
    ``shape = (H, W)`` for every pixel centre of an ``H x W`` image (``(H, W, 3)``).
    """
    if shape is not None:
        ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
    pix = np.stack([xs, ys, np.ones_like(xs)], axis=-1).astype(np.float64)
    return pix @ np.linalg.inv(K).T


def backproject_depth(K: np.ndarray, world_to_cam: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Back-project a depth map (``H x W``, camera z) to world points ``(H, W, 3)``."""
    cam = pixel_rays(K, shape=depth.shape) * depth[..., None]
    cam_to_world = np.linalg.inv(world_to_cam)
    return cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]


def camera_center(world_to_cam: np.ndarray) -> np.ndarray:
    """Camera centre in the world frame: ``-R^T t``."""
    R, t = world_to_cam[:3, :3], world_to_cam[:3, 3]
    return -R.T @ t


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` rotations -> ``(N, 4)`` unit wxyz quaternions (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R, axis1=1, axis2=2)
    cands = np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], 1)
    k = np.argmax(cands, 1)
    q = np.empty((len(R), 4))
    for case in range(4):
        m = k == case
        r = R[m]
        if case == 0:
            s = np.sqrt(1.0 + tr[m]) * 2
            q[m] = np.stack([0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s,
                             (r[:, 1, 0] - r[:, 0, 1]) / s], 1)
        elif case == 1:
            s = np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2
            q[m] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s,
                             (r[:, 0, 2] + r[:, 2, 0]) / s], 1)
        elif case == 2:
            s = np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2
            q[m] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s,
                             (r[:, 1, 2] + r[:, 2, 1]) / s], 1)
        else:
            s = np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2
            q[m] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s,
                             (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s], 1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)  # one sign per rotation: w >= 0
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def voxel_downsample(points: np.ndarray, voxel: float, *attrs: np.ndarray) -> tuple[np.ndarray, ...]:
    """Average ``points`` (and each attribute array) within cubic voxels of side ``voxel``
    (in the points' unit: mm in the world frame, radii in the normalised one).

    Returns ``(points, *attrs)`` with one row per occupied voxel.
    """
    if len(points) == 0:
        return (points,) + attrs
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    out = []
    for a in (points,) + attrs:
        a2 = a.reshape(len(a), -1).astype(np.float64)
        s = np.zeros((len(counts), a2.shape[1]))
        np.add.at(s, inv, a2)
        out.append((s / counts[:, None]).reshape((len(counts),) + a.shape[1:]).astype(a.dtype))
    return tuple(out)
