"""TSDF fusion of depth maps into a mesh (Open3D's tensor ``VoxelBlockGrid``), then
cleaning (keep the largest connected components).

Units: depth maps are camera z in mm, the grid and the mesh are in world mm. The 2DGS
DTU settings are voxel 0.004 and truncation 0.016 in the normalised frame, i.e. times
the scale_mat radius in mm (:func:`default_sizes_mm`). Open3D's camera model has no
skew; the tiny DTU skew (|K[0, 1]| ~ 2e-4 px) is dropped here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline import atomic


@dataclass
class Mesh:
    vertices_mm: np.ndarray  # (V, 3) float64 world mm
    triangles: np.ndarray  # (T, 3) int64
    colors: np.ndarray | None  # (V, 3) float in [0, 1]


def default_sizes_mm(norm_scale_mm: float, voxel_norm: float = 0.004, trunc_norm: float = 0.016) -> tuple[float, float]:
    """``(voxel_mm, trunc_mm)`` from normalised sizes and the scale_mat radius (mm)."""
    return voxel_norm * norm_scale_mm, trunc_norm * norm_scale_mm


def fuse_depth_maps(
    depths_mm: np.ndarray,
    K: np.ndarray,
    world_to_cam: np.ndarray,
    colors: np.ndarray | None,
    voxel_mm: float,
    trunc_mm: float,
    depth_max_mm: float,
    weight_threshold: float = 0.5,
    block_count: int = 40000,
) -> Mesh:
    """Integrate ``(N, H, W)`` depth maps (mm, 0 = no data) and extract the zero level set.

    Args:
        K: ``(N, 3, 3)`` intrinsics; ``world_to_cam``: ``(N, 4, 4)`` world mm -> camera.
        colors: ``(N, H, W, 3)`` in [0, 1] or ``None``.
        voxel_mm, trunc_mm: voxel size and SDF truncation (mm).
        depth_max_mm: depths beyond this are ignored.
        weight_threshold: voxels with less integration weight are not meshed; each view adds
            weight 1, and Open3D meshes weights strictly above the threshold, so 0.5 keeps
            every voxel seen at least once.
    """
    import open3d as o3d
    import open3d.core as o3c

    depths_mm = np.asarray(depths_mm, np.float32)
    if depths_mm.ndim != 3 or K.shape != (len(depths_mm), 3, 3) or world_to_cam.shape != (len(depths_mm), 4, 4):
        raise ValueError(f"fuse_depth_maps: need (N,H,W) depths with (N,3,3) K and (N,4,4) poses, got "
                         f"{depths_mm.shape}, {K.shape}, {world_to_cam.shape}")
    if not np.all(np.isfinite(depths_mm)):
        raise ValueError("fuse_depth_maps: depth maps have non-finite values (use 0 for no data)")
    if voxel_mm <= 0 or trunc_mm <= voxel_mm:
        raise ValueError(f"fuse_depth_maps: need 0 < voxel_mm < trunc_mm, got {voxel_mm}, {trunc_mm}")
    with_color = colors is not None
    names, dtypes, channels = ["tsdf", "weight"], [o3c.float32, o3c.float32], [1, 1]
    if with_color:
        names.append("color")
        dtypes.append(o3c.float32)
        channels.append(3)
    device = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=tuple(names), attr_dtypes=tuple(dtypes),
                                        attr_channels=tuple(channels), voxel_size=float(voxel_mm),
                                        block_resolution=8, block_count=block_count, device=device)
    for i in range(len(depths_mm)):
        if not np.any((depths_mm[i] > 0) & (depths_mm[i] < depth_max_mm)):
            continue  # Open3D aborts on a depth map that touches no block
        depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depths_mm[i])))
        intr = o3c.Tensor(np.asarray(K[i], np.float64).copy())
        intr[0, 1] = 0.0  # Open3D has no skew
        extr = o3c.Tensor(np.asarray(world_to_cam[i], np.float64))
        blocks = vbg.compute_unique_block_coordinates(depth, intr, extr, depth_scale=1.0,
                                                      depth_max=float(depth_max_mm),
                                                      trunc_voxel_multiplier=float(trunc_mm / voxel_mm))
        if with_color:
            color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(colors[i], dtype=np.float32)))
            vbg.integrate(blocks, depth, color, intr, intr, extr, depth_scale=1.0, depth_max=float(depth_max_mm),
                          trunc_voxel_multiplier=float(trunc_mm / voxel_mm))
        else:
            vbg.integrate(blocks, depth, intr, extr, depth_scale=1.0, depth_max=float(depth_max_mm),
                          trunc_voxel_multiplier=float(trunc_mm / voxel_mm))
    try:
        mesh = vbg.extract_triangle_mesh(weight_threshold=float(weight_threshold)).to_legacy()
    except RuntimeError as exc:  # Open3D fails on an empty extraction instead of returning nothing
        raise ValueError(f"fuse_depth_maps: no surface above weight {weight_threshold} ({exc})") from exc
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    tris = np.asarray(mesh.triangles, dtype=np.int64)
    cols = np.asarray(mesh.vertex_colors, dtype=np.float64) if with_color and mesh.has_vertex_colors() else None
    return Mesh(verts, tris, cols)


def keep_largest_components(mesh: Mesh, num_clusters: int = 1, min_fraction: float = 0.0) -> Mesh:
    """Keep the ``num_clusters`` largest triangle-connected components, and among those
    only components with at least ``min_fraction`` of the largest one's triangles; drop
    unreferenced vertices."""
    import open3d as o3d

    if len(mesh.triangles) == 0:
        return mesh
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices_mm),
                                  o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    labels, sizes, _ = m.cluster_connected_triangles()
    labels, sizes = np.asarray(labels), np.asarray(sizes)
    order = np.argsort(-sizes)[:max(1, num_clusters)]
    order = order[sizes[order] >= min_fraction * sizes[order[0]]]
    tris = mesh.triangles[np.isin(labels, order)]
    used = np.unique(tris)
    remap = np.full(len(mesh.vertices_mm), -1, np.int64)
    remap[used] = np.arange(len(used))
    cols = mesh.colors[used] if mesh.colors is not None else None
    return Mesh(mesh.vertices_mm[used], remap[tris], cols)


def write_mesh(path, mesh: Mesh) -> None:
    """Binary PLY via Open3D, atomically (temp file in the same folder, then rename)."""
    from pathlib import Path

    import open3d as o3d

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices_mm),
                                  o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    if mesh.colors is not None:
        m.vertex_colors = o3d.utility.Vector3dVector(np.clip(mesh.colors, 0, 1))
    with atomic.atomic_file(path, suffix=".ply") as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), m, write_ascii=False):
            raise OSError(f"{path}: Open3D could not write the mesh")
