"""Ground-truth folders in the official DTU "SampleSet/MVS Data" layout.

One layout, one reader, for the official DTU files and for synthetic scenes::

    GT_ROOT/ObsMask/ObsMask{scan}_10.mat     ObsMask (X,Y,Z bool voxels), BB (2x3 mm), Res (mm)
    GT_ROOT/ObsMask/Plane{scan}.mat          P (4x1): [x, y, z, 1] . P > 0 is above the ground
    GT_ROOT/Points/stl/stl{scan:03}_total.ply   dense GT points (mm, ~0.2 mm apart)
    GT_ROOT/mesh.ply                         synthetic scenes only: the GT mesh (mm)

Voxel ``(i, j, k)`` of ObsMask is centred at ``BB[0] + Res * (i, j, k)``: a point ``p`` falls in
voxel ``round((p - BB[0]) / Res)``, as in the evaluation script.
"""
from __future__ import annotations

import io
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io
import scipy.ndimage

from pipeline import ply
from pipeline.errors import InputError, MissingInputError
from pipeline.evaluation.sampling import (
    MeshError,
    check_mesh,
    derived_seed,
    radius_downsample,
    sample_mesh,
)

# The official files are named "_10" after the 10 mm margin of their observation mask.
# With one voxel of dilation the margin here is one voxel, so 10 mm voxels match it.
DEFAULT_RES_MM = 10.0
# Replaces scipy's .mat header text, which holds the time of writing: the same GT gives
# the same bytes (DVC hashes outputs).
MAT_DESCRIPTION = b"MATLAB 5.0 MAT-file, written by pipeline.evaluation.gt"
# The stl points' thinning order is drawn from the writer's seed and this purpose, never
# equal to the evaluator's order for the same seed: with equal orders a mesh with the GT
# mesh's layout gets exactly the GT points back and scores ~1e-5 mm instead of its true
# ~0.07 mm discretisation floor.
GT_SEED_PURPOSE = "ground-truth points"


class GroundTruthError(InputError):
    """Missing or malformed ground-truth files; the message names the file."""


@dataclass
class GroundTruth:
    """Ground truth of one scan, in world millimetres."""

    scan_id: int
    points_mm: np.ndarray  # (N, 3) float64, the stl points
    obs_mask: np.ndarray  # (X, Y, Z) bool
    bb_mm: np.ndarray  # (2, 3) float64: min corner, max corner (float32 values, as the script casts)
    res_mm: float
    plane: np.ndarray  # (4,) float64
    root: Path

    def voxel_index(self, points_mm: np.ndarray) -> np.ndarray:
        """ObsMask voxel of each point (int64 (N, 3), may be out of range)."""
        return np.around((points_mm - self.bb_mm[0]) / self.res_mm).astype(np.int64)

    def box_and_observed(self, points_mm: np.ndarray, patch_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Step 3 of the protocol: ``(inbound (N,), observed (M,))`` where ``inbound`` marks
        points with ``BB[0] - patch <= p < BB[1] + 2 patch`` and ``observed`` marks which of
        those ``M`` in-box points fall in a set ObsMask voxel."""
        bb = self.bb_mm
        inbound = ((points_mm >= bb[0] - patch_mm) & (points_mm < bb[1] + 2 * patch_mm)).all(axis=1)
        vox = self.voxel_index(points_mm[inbound])
        in_grid = ((vox >= 0) & (vox < np.array(self.obs_mask.shape))).all(axis=1)
        observed = np.zeros(len(vox), bool)
        observed[in_grid] = self.obs_mask[tuple(vox[in_grid].T)]
        return inbound, observed

    def above_plane(self, points_mm: np.ndarray) -> np.ndarray:
        """``[x, y, z, 1] . P > 0``, per coordinate (no BLAS call: see ``cull_vertices``)."""
        P = self.plane
        return points_mm[:, 0] * P[0] + points_mm[:, 1] * P[1] + points_mm[:, 2] * P[2] + P[3] > 0


def paths(gt_dir: str | Path, scan_id: int) -> dict[str, Path]:
    root = Path(gt_dir)
    return {
        "obs_mask": root / "ObsMask" / f"ObsMask{scan_id}_10.mat",
        "plane": root / "ObsMask" / f"Plane{scan_id}.mat",
        "points": root / "Points" / "stl" / f"stl{scan_id:03d}_total.ply",
        "mesh": root / "mesh.ply",
    }


# --- PLY ---------------------------------------------------------------------------------


def _xyz_float32(points: np.ndarray) -> dict[str, np.ndarray]:
    return {k: np.asarray(points[:, i], np.float32) for i, k in enumerate("xyz")}


def write_ply_points(path: str | Path, points_mm: np.ndarray) -> None:
    """Binary PLY of points (float32 x, y, z), written atomically."""
    ply.write(path, _xyz_float32(points_mm))


def write_ply_mesh(path: str | Path, vertices_mm: np.ndarray, triangles: np.ndarray) -> None:
    """Binary PLY triangle mesh (float32 vertices, int32 faces), written atomically."""
    ply.write(path, _xyz_float32(vertices_mm), faces=triangles)


def read_points(path: str | Path) -> np.ndarray:
    """Points of a PLY (or any point cloud open3d reads) as float64 ``(N, 3)``; N > 0."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: file not found")
    if path.suffix.lower() == ".ply":
        ply.check_file(path, GroundTruthError)
    pts = np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float64)
    if len(pts) == 0:
        raise GroundTruthError(f"{path}: no points (empty or unreadable point cloud)")
    if not np.isfinite(pts).all():
        raise GroundTruthError(f"{path}: {int((~np.isfinite(pts).all(1)).sum())} points are not finite")
    return pts


def read_mesh(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices float64 (V,3), triangles int64 (F,3))`` of a mesh file (PLY/OBJ/...)."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: file not found")
    if path.suffix.lower() == ".ply":
        ply.check_file(path, MeshError)
    m = o3d.io.read_triangle_mesh(str(path))
    vertices = np.asarray(m.vertices, dtype=np.float64)
    if len(vertices) == 0:  # open3d returns an empty mesh (and only warns) on read failures
        raise MeshError(f"{path}: no vertices read (empty, unreadable or unsupported mesh file)")
    return vertices, np.asarray(m.triangles, dtype=np.int64)


# --- reader -------------------------------------------------------------------------------


def _loadmat(path: Path, keys: tuple[str, ...]) -> dict:
    if not path.is_file():
        raise MissingInputError(f"{path}: file not found")
    try:
        data = scipy.io.loadmat(str(path))
    except Exception as exc:  # scipy raises several types for corrupt files
        raise GroundTruthError(f"{path}: not a readable MATLAB .mat file ({exc})") from exc
    missing = [k for k in keys if k not in data]
    if missing:
        raise GroundTruthError(f"{path}: missing variable(s) {missing}")
    return data


def find_scan_ids(gt_dir: str | Path) -> list[int]:
    folder = Path(gt_dir) / "ObsMask"
    if not folder.is_dir():
        return []
    ids = (re.fullmatch(r"ObsMask(\d+)_10\.mat", p.name) for p in folder.iterdir())
    return sorted(int(m.group(1)) for m in ids if m)


def read_ground_truth(gt_dir: str | Path, scan_id: int | None = None) -> GroundTruth:
    """Read and check a GT folder; ``scan_id`` may be omitted when it holds one scan."""
    root = Path(gt_dir)
    if not root.is_dir():
        raise MissingInputError(f"{root}: ground-truth folder not found")
    if scan_id is None:
        ids = find_scan_ids(root)
        if len(ids) != 1:
            raise GroundTruthError(
                f"{root / 'ObsMask'}: cannot infer the scan id, found {len(ids)} ObsMask*_10.mat files "
                f"{ids[:10]}; give the scan id"
            )
        scan_id = ids[0]
    p = paths(root, int(scan_id))
    obs = _loadmat(p["obs_mask"], ("ObsMask", "BB", "Res"))
    mask = np.asarray(obs["ObsMask"]).astype(bool)
    if mask.ndim != 3 or mask.size == 0:
        raise GroundTruthError(f"{p['obs_mask']}: ObsMask must be a non-empty 3-D volume, got shape {mask.shape}")
    # The script casts BB to float32; do the same so voxel indices match it exactly.
    bb = np.asarray(obs["BB"], dtype=np.float32).astype(np.float64)
    if bb.shape != (2, 3) or not np.isfinite(bb).all() or not (bb[1] > bb[0]).all():
        raise GroundTruthError(f"{p['obs_mask']}: BB must be a finite 2x3 [min; max] box, got {bb.tolist()}")
    res = np.asarray(obs["Res"], dtype=np.float64).ravel()
    if res.size != 1 or not np.isfinite(res[0]) or res[0] <= 0:
        raise GroundTruthError(f"{p['obs_mask']}: Res must be one positive voxel size (mm), got {res.tolist()}")
    plane = np.asarray(_loadmat(p["plane"], ("P",))["P"], dtype=np.float64).ravel()
    if plane.size != 4 or not np.isfinite(plane).all() or not np.any(plane[:3]):
        raise GroundTruthError(f"{p['plane']}: P must be a finite 4-vector with a non-zero normal, got {plane.tolist()}")
    points = read_points(p["points"])
    return GroundTruth(scan_id=int(scan_id), points_mm=points, obs_mask=mask, bb_mm=bb, res_mm=float(res[0]),
                       plane=plane, root=root)


# --- writer -------------------------------------------------------------------------------


def mat_bytes(data: dict) -> bytes:
    """A compressed MATLAB 5 file of ``data`` whose bytes depend on ``data`` only (the
    116-byte header text, a timestamp in scipy's, is :data:`MAT_DESCRIPTION`)."""
    buf = io.BytesIO()
    scipy.io.savemat(buf, data, do_compression=True)
    return MAT_DESCRIPTION.ljust(116, b" ") + buf.getvalue()[116:]


def write_ground_truth(
    gt_dir: str | Path,
    scan_id: int,
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    plane: np.ndarray,
    observed_points_mm: np.ndarray | None = None,
    res_mm: float = DEFAULT_RES_MM,
    spacing_mm: float = 0.2,
    seed: int = 0,
) -> dict[str, Path]:
    """Write a GT folder for a mesh (synthetic scenes): the stl points, ObsMask, Plane, mesh.

    * stl points: the mesh sampled like the evaluation samples data (vertices plus a
      ``spacing_mm`` triangle grid), then greedily radius-downsampled at ``spacing_mm``
      (the official stl points are "reduced to 0.2 mm neighbourhood density") in an
      order drawn from ``derived_seed(seed, GT_SEED_PURPOSE)``, independent of the
      evaluator's order for any seed.
    * ObsMask: voxels of size ``res_mm`` holding an observed point (default: every stl
      point), dilated by one voxel (26-neighbourhood), so the mask reaches at least one
      voxel beyond the observed surface. BB: the bounds of the points, grown by two voxels.
    * Plane: ``plane`` (4,), points with ``[x, y, z, 1] . plane > 0`` are above the ground.

    Existing files are replaced; each file is written to a temp file first and all are
    renamed into place at the end; the same arguments give the same bytes. Returns the
    paths written (see :func:`paths`).
    """
    V, F = check_mesh(vertices_mm, triangles, name="ground-truth mesh")
    plane = np.asarray(plane, dtype=np.float64).ravel()
    if plane.size != 4 or not np.isfinite(plane).all() or not np.any(plane[:3]):
        raise ValueError(f"ground plane must be a finite 4-vector with a non-zero normal, got {plane.tolist()}")
    if not (np.isfinite(res_mm) and res_mm > 0 and np.isfinite(spacing_mm) and spacing_mm > 0):
        raise ValueError(f"res_mm and spacing_mm must be positive, got {res_mm}, {spacing_mm}")
    samples = sample_mesh(V, F, spacing_mm)
    points = samples[radius_downsample(samples, spacing_mm, seed=derived_seed(seed, GT_SEED_PURPOSE))]
    observed = points if observed_points_mm is None else np.asarray(observed_points_mm, dtype=np.float64)
    if observed.ndim != 2 or observed.shape[1] != 3 or len(observed) == 0 or not np.isfinite(observed).all():
        raise ValueError(f"observed_points_mm must be a non-empty finite (N, 3) array, got shape {observed.shape}")

    lo = np.minimum(points.min(axis=0), observed.min(axis=0)) - 2 * res_mm
    hi = np.maximum(points.max(axis=0), observed.max(axis=0)) + 2 * res_mm
    bb = np.stack([lo, hi]).astype(np.float32).astype(np.float64)  # the reader casts to float32
    shape = np.ceil((bb[1] - bb[0]) / res_mm).astype(np.int64) + 1
    mask = np.zeros(tuple(shape), bool)
    idx = np.around((observed - bb[0]) / res_mm).astype(np.int64)  # >= 2 voxels inside BB
    mask[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    mask = scipy.ndimage.binary_dilation(mask, structure=np.ones((3, 3, 3), bool))

    out = paths(gt_dir, int(scan_id))
    staged: list[tuple[Path, Path]] = []
    try:
        for key, writer in (
            ("points", lambda f: Path(f).write_bytes(ply.encode(_xyz_float32(points)))),
            ("mesh", lambda f: Path(f).write_bytes(ply.encode(_xyz_float32(V), F))),
            ("obs_mask", lambda f: Path(f).write_bytes(mat_bytes({"ObsMask": mask, "BB": bb,
                                                                   "Res": np.array([[res_mm]])}))),
            ("plane", lambda f: Path(f).write_bytes(mat_bytes({"P": plane.reshape(4, 1)}))),
        ):
            final = out[key]
            final.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", dir=final.parent)
            os.close(fd)
            staged.append((Path(tmp), final))
            writer(tmp)
        for tmp, final in staged:
            os.replace(tmp, final)
    finally:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
    return out
