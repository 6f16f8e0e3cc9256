"""Surfel PLY files, in the world frame (mm): the 2DGS ``point_cloud.ply`` layout (read and
write) and the 3DGS layout for viewers (write only)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from pipeline import atomic, ply
from pipeline.surfels.params import SurfelInitError, SurfelParams


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
    ply.check(raw, path, SurfelInitError)
    body = raw[end + len(b"end_header\n"):]
    if len(body) != count * len(names) * 4:
        raise SurfelInitError(f"{path}: {len(body)} bytes for {count} surfels; every property must be a float")
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
