"""Trainable 2D Gaussian surfels: parameters, initialisation from an init cloud, PLY I/O.

Frame and units: training runs in the scene's **normalised frame** (the unit sphere of
``scale_mat``: ``x_world_mm = norm_to_world @ x_norm``), so learning rates, thresholds and
sizes mean the same on a 5 mm and a 500 mm object. Files are written in the **world frame,
mm** (centres and scales multiplied by the scale_mat radius), so that a surfel PLY overlays
the mesh and the ground truth.

Parameters (as 2DGS): ``means (P,3)``, ``log_scales (P,2)``, ``quats (P,4)`` (wxyz, not
necessarily unit), ``opacity_logits (P,)``, ``sh_dc (P,1,3)``, ``sh_rest (P,K-1,3)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from pipeline import atomic
from pipeline.errors import InputError
from pipeline.geometry import rotmat_to_quat
from pipeline.rasterizer import Surfels
from pipeline.rasterizer.project import SH_C0

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


class SurfelInitError(InputError):
    """The init cloud cannot seed surfels (names the file and the problem)."""


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] -> the SH DC coefficient whose evaluation gives that colour."""
    return (np.asarray(rgb, np.float64) - 0.5) / SH_C0


def frames_from_normals(normals: np.ndarray) -> np.ndarray:
    """``(N, 3)`` unit normals -> ``(N, 3, 3)`` rotations whose third column is the normal
    (tangent axes: any orthonormal pair; a surfel is isotropic at init)."""
    n = np.asarray(normals, np.float64)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    # Helper axis least aligned with n, so the cross product never degenerates.
    helper = np.zeros_like(n)
    helper[np.arange(len(n)), np.argmin(np.abs(n), axis=1)] = 1.0
    tu = np.cross(helper, n)
    tu /= np.linalg.norm(tu, axis=1, keepdims=True)
    tv = np.cross(n, tu)
    return np.stack([tu, tv, n], axis=2)


def random_quats(n: int, rng: np.random.Generator) -> np.ndarray:
    """Uniformly random unit quaternions (2DGS draws random rotations)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def knn_scales(points: np.ndarray, k: int = 3) -> np.ndarray:
    """2DGS's initial scale: ``sqrt(mean squared distance to the k nearest neighbours)``.

    Coincident points would give 0; the floor is a thousandth of the cloud's median
    spacing (or 1e-7 for a single point), so every log-scale is finite."""
    n = len(points)
    if n == 1:
        return np.full(1, 1e-2)
    kk = min(k, n - 1)
    d, _ = cKDTree(points).query(points, k=kk + 1)
    d = d[:, 1:]
    s = np.sqrt(np.mean(d * d, axis=1))
    floor = max(float(np.median(s)) * 1e-3, 1e-7)
    return np.maximum(s, floor)


@dataclass
class SurfelParams:
    """The optimised tensors (normalised frame), each ``requires_grad`` leaf."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor

    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree_max(self) -> int:
        return int(round(math.sqrt(self.sh_rest.shape[1] + 1))) - 1

    def tensors(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k) for k in PARAM_NAMES}

    def replace(self, new: dict[str, torch.Tensor]) -> None:
        for k, v in new.items():
            setattr(self, k, v)

    def surfels(self, sh_degree: int, min_scale: float = 0.0) -> Surfels:
        """Activated surfels for the rasterizer (normalised frame)."""
        features = torch.cat([self.sh_dc, self.sh_rest], dim=1)
        scales = torch.exp(self.log_scales)
        if min_scale > 0:
            scales = scales.clamp_min(min_scale)
        return Surfels(self.means, self.quats, scales, torch.sigmoid(self.opacity_logits), features, sh_degree=sh_degree)


def init_params(points_norm: np.ndarray, normals: np.ndarray | None, colors: np.ndarray, sh_degree: int,
                opacity: float, rng: np.random.Generator, dtype=torch.float32, where: str = "init cloud") -> SurfelParams:
    """Surfels seeded from a cloud (normalised frame): centres at the points, normal from
    the point normal (random rotation when ``normals`` is None, as 2DGS), both log-scales
    from :func:`knn_scales`, colour as SH DC (higher bands 0), opacity ``opacity``."""
    points_norm = np.asarray(points_norm, np.float64)
    n = len(points_norm)
    if n == 0:
        raise SurfelInitError(f"{where}: no point to seed surfels from (an init stage that matched nothing?)")
    if not np.all(np.isfinite(points_norm)):
        raise SurfelInitError(f"{where}: non-finite point coordinates")
    if not 0 < opacity < 1:
        raise ValueError(f"initial opacity must be in (0, 1), got {opacity}")
    quats = random_quats(n, rng) if normals is None else rotmat_to_quat(frames_from_normals(normals))
    log_s = np.log(knn_scales(points_norm))
    k = (sh_degree + 1) ** 2

    def leaf(a) -> torch.Tensor:
        return torch.tensor(np.asarray(a), dtype=dtype).requires_grad_(True)

    return SurfelParams(
        means=leaf(points_norm),
        log_scales=leaf(np.repeat(log_s[:, None], 2, axis=1)),
        quats=leaf(quats),
        opacity_logits=leaf(np.full(n, math.log(opacity / (1 - opacity)))),
        sh_dc=leaf(rgb_to_sh_dc(colors)[:, None, :]),
        sh_rest=leaf(np.zeros((n, k - 1, 3))),
    )


# 2DGS's point_cloud.ply layout: x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..1 rot_0..3
# (f_rest channel-major: all coefficients of R, then G, then B; opacity as logit, scales as log).
def ply_attribute_names(num_rest: int) -> list[str]:
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * num_rest)] + ["opacity", "scale_0", "scale_1"]
            + [f"rot_{i}" for i in range(4)])


def _world_columns(params: SurfelParams, norm_to_world: np.ndarray) -> dict[str, np.ndarray]:
    """Per-surfel float64 columns in the world frame: ``means``, ``normals``, ``dc``,
    ``rest`` (channel-major), ``opacity`` (logit), ``log_scales`` and unit ``quats`` (wxyz)."""
    from pipeline.rasterizer.project import quat_to_rotmat

    S = np.asarray(norm_to_world, np.float64)
    with torch.no_grad():
        quats = torch.nn.functional.normalize(params.quats.double(), dim=1).numpy()
        return {
            "means": params.means.double().numpy() @ S[:3, :3].T + S[:3, 3],
            "normals": quat_to_rotmat(torch.from_numpy(quats))[:, :, 2].numpy(),
            "dc": params.sh_dc.double().numpy().reshape(params.num, 3),
            "rest": params.sh_rest.double().numpy().transpose(0, 2, 1).reshape(params.num, -1),
            "opacity": params.opacity_logits.double().numpy()[:, None],
            "log_scales": params.log_scales.double().numpy() + math.log(float(S[0, 0])),
            "quats": quats,
        }


def _write_float_ply(path: str | Path, names: list[str], columns: list[np.ndarray], comment: str) -> Path:
    """A binary little-endian PLY of one ``vertex`` element, every property float32 (atomic)."""
    data = np.concatenate(columns, axis=1).astype("<f4")
    header = (f"ply\nformat binary_little_endian 1.0\ncomment {comment}\nelement vertex {len(data)}\n"
              + "".join(f"property float {n}\n" for n in names) + "end_header\n")
    path = Path(path)
    atomic.write_bytes(path, header.encode("ascii") + data.tobytes())
    return path


def write_surfel_ply(path: str | Path, params: SurfelParams, norm_to_world: np.ndarray) -> Path:
    """Write surfels in the world frame (mm) with 2DGS's attribute names (atomic)."""
    c = _world_columns(params, norm_to_world)
    return _write_float_ply(path, ply_attribute_names(params.sh_rest.shape[1]),
                            [c["means"], c["normals"], c["dc"], c["rest"], c["opacity"], c["log_scales"], c["quats"]],
                            "gcgs surfels (2DGS layout): world frame, millimetres")


# A viewer of 3DGS files draws 3D Gaussians; a surfel is flat, so its third axis (the
# normal) gets this fraction of its smaller in-plane scale: thin enough to look like the
# disc, relative so it means the same in any unit and stays far from float32 underflow in
# a viewer's covariance (gsplat's 2DGS trainer keeps an unused third log-scale instead).
THICKNESS_RATIO = 1e-3


def splats_3dgs_attribute_names(num_rest: int) -> list[str]:
    """The 3DGS ``point_cloud.ply`` layout: as :func:`ply_attribute_names` with ``scale_2``."""
    names = ply_attribute_names(num_rest)
    i = names.index("scale_1") + 1
    return names[:i] + ["scale_2"] + names[i:]


def write_splats_3dgs_ply(path: str | Path, params: SurfelParams, norm_to_world: np.ndarray) -> Path:
    """Write surfels for 3DGS viewers (atomic): the standard layout
    (:func:`splats_3dgs_attribute_names`; log scales, logit opacity, wxyz unit quaternions,
    SH channel-major), in the world frame and units, each surfel a Gaussian whose third
    log-scale (along its normal) is ``log(THICKNESS_RATIO)`` below its smaller one."""
    c = _world_columns(params, norm_to_world)
    thick = c["log_scales"].min(axis=1, keepdims=True) + math.log(THICKNESS_RATIO)
    return _write_float_ply(path, splats_3dgs_attribute_names(params.sh_rest.shape[1]),
                            [c["means"], c["normals"], c["dc"], c["rest"], c["opacity"], c["log_scales"], thick,
                             c["quats"]], "gcgs surfels as 3D Gaussians (3DGS layout): world frame")


def read_surfel_ply(path: str | Path, norm_to_world: np.ndarray, dtype=torch.float32) -> SurfelParams:
    """Read a surfel PLY written by :func:`write_surfel_ply` back into the normalised frame."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header\n")
    if not raw.startswith(b"ply\n") or end < 0:
        raise SurfelInitError(f"{path}: not a PLY file")
    header = raw[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise SurfelInitError(f"{path}: only binary little-endian PLY is supported")
    names = [ln.split()[-1] for ln in header if ln.startswith("property")]
    counts = [ln.split()[-1] for ln in header if ln.startswith("element vertex")]
    if len(counts) != 1 or not counts[0].isdigit():
        raise SurfelInitError(f"{path}: no valid 'element vertex N' line in the header")
    count = int(counts[0])
    num_rest = sum(n.startswith("f_rest_") for n in names) // 3
    if names != ply_attribute_names(num_rest):
        raise SurfelInitError(f"{path}: attributes {names[:12]}... are not the 2DGS surfel layout")
    body = raw[end + len(b"end_header\n"):]
    if len(body) != count * len(names) * 4:
        raise SurfelInitError(f"{path}: truncated ({len(body)} bytes for {count} surfels)")
    data = np.frombuffer(body, "<f4").reshape(count, len(names)).astype(np.float64)
    if not np.all(np.isfinite(data)):
        bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
        raise SurfelInitError(f"{path}: {len(bad)} surfel(s) hold NaN or infinite values (first: surfel {bad[0]})")
    S = np.asarray(norm_to_world, np.float64)
    s = float(S[0, 0])
    means = (data[:, 0:3] - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    rest = data[:, 9:9 + 3 * num_rest].reshape(count, 3, num_rest).transpose(0, 2, 1)
    o = 9 + 3 * num_rest

    def leaf(a) -> torch.Tensor:
        return torch.tensor(np.ascontiguousarray(a), dtype=dtype).requires_grad_(True)

    return SurfelParams(means=leaf(means), log_scales=leaf(data[:, o + 1:o + 3] - math.log(s)),
                        quats=leaf(data[:, o + 3:o + 7]), opacity_logits=leaf(data[:, o]),
                        sh_dc=leaf(data[:, 6:9][:, None, :]), sh_rest=leaf(rest))
