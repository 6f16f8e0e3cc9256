"""TSDF fusion of depth maps into a mesh (Open3D's tensor ``VoxelBlockGrid``), then
cleaning (keep every connected component not much smaller than the largest).

Units: depth maps are camera z in mm, the grid and the mesh are in world mm. Voxel and
truncation sizes come from :class:`~pipeline.config.mesh.MeshConfig` in the normalised frame
(2DGS on DTU: 0.004 and 0.016), i.e. times the scale_mat radius in mm. Open3D's camera
model has no skew; the tiny DTU skew (|K[0, 1]| ~ 2e-4 px) is dropped here.

Grazing pixels get a longer truncation. Open3D's projective TSDF skips a voxel more than the
truncation behind the depth *along the ray*; behind a surface seen at incidence theta, the
voxels within one voxel of it along its normal lie 1/cos(theta) further along the ray, so at
grazing incidence no voxel behind the surface is written and no zero crossing forms: with
exact depth, the mesh missed most surface seen beyond 80 degrees (docs/evaluation.md). A
pixel whose surface (the normal of its depth map's neighbourhood) is seen beyond
``GRAZING_INCIDENCE_DEG`` is fused with ``GRAZING_TRUNC_FACTOR`` x the truncation, every other
pixel with the truncation itself, so thin parts seen face-on are not fattened.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import geometry, ply
from pipeline.config.mesh import MeshConfig
from pipeline.data.dtu import load_scene
from pipeline.data.scene import Scene
from pipeline.errors import InputError
from pipeline.init.io import load_init_depths, stacked_depths_mm
from pipeline.meshing import region as bounding
from pipeline.meshing.holes import fill_supported_holes

# Pixels whose surface is seen beyond this incidence are fused with a longer truncation
# (module docstring; measured in docs/evaluation.md, "Exact depth through the same meshing").
GRAZING_INCIDENCE_DEG = 80.0
GRAZING_TRUNC_FACTOR = 4.0

# Cleaning that drops more than this fraction of the fused triangles gets a warning: a
# real object may have lost a part (raise min_component_fraction's reach by lowering it).
DROPPED_WARNING_FRACTION = 0.25


class FusionError(InputError):
    """Depth maps that fuse into no surface."""


@dataclass
class Mesh:
    vertices_mm: np.ndarray  # (V, 3) float64 world mm
    triangles: np.ndarray  # (T, 3) int64
    colors: np.ndarray | None  # (V, 3) float in [0, 1]


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
        voxel_mm, trunc_mm: voxel size and SDF truncation (mm); pixels whose surface is seen
            beyond ``GRAZING_INCIDENCE_DEG`` (:func:`grazing_pixels`) are fused with
            ``GRAZING_TRUNC_FACTOR`` x ``trunc_mm``.
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
        intr = o3c.Tensor(open3d_intrinsics(K[i]))
        extr = o3c.Tensor(np.asarray(world_to_cam[i], np.float64))
        if with_color:
            color = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(colors[i], dtype=np.float32)))
        grazing = grazing_pixels(depths_mm[i], K[i], GRAZING_INCIDENCE_DEG)
        for part, trunc in ((~grazing, trunc_mm), (grazing, GRAZING_TRUNC_FACTOR * trunc_mm)):
            d = np.where(part, depths_mm[i], np.float32(0.0))
            if not np.any((d > 0) & (d < depth_max_mm)):
                continue  # Open3D aborts on a depth map that touches no block
            depth = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(d)))
            multiplier = float(trunc / voxel_mm)
            try:
                blocks = vbg.compute_unique_block_coordinates(depth, intr, extr, depth_scale=1.0,
                                                              depth_max=float(depth_max_mm),
                                                              trunc_voxel_multiplier=multiplier)
            except RuntimeError as exc:
                # Open3D reads every 4th pixel here and aborts when none of them has depth (a
                # few grazing pixels): take the blocks from every pixel's point instead.
                if "No block is touched" not in str(exc):
                    raise
                points = geometry.backproject_depth(K[i], world_to_cam[i], d)[(d > 0) & (d < depth_max_mm)]
                cloud = o3d.t.geometry.PointCloud(o3c.Tensor(points.astype(np.float32)))
                blocks = vbg.compute_unique_block_coordinates(cloud, trunc_voxel_multiplier=multiplier)
            if with_color:
                vbg.integrate(blocks, depth, color, intr, intr, extr, depth_scale=1.0,
                              depth_max=float(depth_max_mm), trunc_voxel_multiplier=multiplier)
            else:
                vbg.integrate(blocks, depth, intr, extr, depth_scale=1.0, depth_max=float(depth_max_mm),
                              trunc_voxel_multiplier=multiplier)
    try:
        mesh = vbg.extract_triangle_mesh(weight_threshold=float(weight_threshold)).to_legacy()
    except RuntimeError as exc:  # Open3D fails on an empty extraction instead of returning nothing
        raise FusionError(f"fuse_depth_maps: no surface above weight {weight_threshold} ({exc})") from exc
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    tris = np.asarray(mesh.triangles, dtype=np.int64)
    cols = np.asarray(mesh.vertex_colors, dtype=np.float64) if with_color and mesh.has_vertex_colors() else None
    return canonical_order(Mesh(verts, tris, cols))


def grazing_pixels(depth_mm: np.ndarray, K: np.ndarray, incidence_deg: float) -> np.ndarray:
    """``(H, W)`` bool: pixels of a depth map (camera z, 0 = none; integer pixel centres) whose
    surface is seen beyond ``incidence_deg`` from its normal. The normal is the cross product
    of the central differences of the back-projected points along x and y; a pixel without
    depth at any of its four neighbours has no normal and is not grazing."""
    d = np.asarray(depth_mm, np.float64)
    H, W = d.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    P = np.stack([(u - K[0, 2]) / K[0, 0] * d, (v - K[1, 2]) / K[1, 1] * d, d], -1)
    ok = d > 0
    dx, dy = np.zeros_like(P), np.zeros_like(P)
    dx[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dy[1:-1] = P[2:] - P[:-2]
    has = np.zeros_like(ok)
    has[1:-1, 1:-1] = ok[1:-1, 2:] & ok[1:-1, :-2] & ok[2:, 1:-1] & ok[:-2, 1:-1]
    n = np.cross(dx, dy)
    n_len = np.linalg.norm(n, axis=-1)
    p_len = np.linalg.norm(P, axis=-1)
    cos = np.abs((n * P).sum(-1)) / np.maximum(n_len * p_len, 1e-300)
    return ok & has & (n_len > 0) & (cos < np.cos(np.radians(incidence_deg)))


def fusion_masks(scene: Scene, cfg: MeshConfig) -> np.ndarray | None:
    """``(N, H, W)`` bool masks that cut the depth fused at ``scene``'s input views: the scene's
    masks when ``cfg.masks`` and it has them, else ``None`` (nothing cut). One rule for the mesh
    stage and the exact-depth yardstick, so the two cannot drift apart."""
    return scene.masks if (cfg.masks and scene.masks is not None) else None


def open3d_intrinsics(K: np.ndarray) -> np.ndarray:
    """The project's K (pixel centres at integer coordinates) as Open3D's TSDF integration
    reads it: it looks a projected point up in depth pixel ``floor(u)``, i.e. pixel ``u``
    covers ``[u, u + 1)`` with its centre at ``u + 0.5``, so the principal point moves by half
    a pixel. Without it a slanted surface is fused off by about half a pixel's depth change
    (0.11 mm at 30 degrees, 0.21 mm at 60, 685 mm away at 800x600: tests/test_tsdf.py).
    Open3D has no skew."""
    out = np.asarray(K, np.float64).copy()
    out[0, 1] = 0.0
    out[0, 2] += 0.5
    out[1, 2] += 0.5
    return out


def canonical_order(mesh: Mesh) -> Mesh:
    """The same mesh with its vertices sorted by (x, y, z), each triangle's indices rotated
    to start at its smallest (the winding, hence the normal, is kept) and the triangles
    sorted. Open3D's block hash map extracts vertices in an order that varies from run to
    run; in this order the same surface is written with the same bytes."""
    v = mesh.vertices_mm
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    tris = rank[mesh.triangles]
    if len(tris):
        shift = np.argmin(tris, axis=1)
        tris = tris[np.arange(len(tris))[:, None], (shift[:, None] + np.arange(3)) % 3]
        tris = tris[np.lexsort((tris[:, 2], tris[:, 1], tris[:, 0]))]
    cols = mesh.colors[order] if mesh.colors is not None else None
    return Mesh(v[order], tris, cols)


def keep_components(mesh: Mesh, min_fraction: float) -> tuple[Mesh, dict]:
    """Keep every triangle-connected component with at least ``min_fraction`` of the
    largest one's triangles (0 keeps all, 1 only the largest and its equals); drop
    unreferenced vertices. Returns the mesh and facts: triangle and component counts
    fused and kept."""
    import open3d as o3d

    if len(mesh.triangles) == 0:
        return mesh, {"triangles_fused": 0, "triangles_kept": 0, "components_fused": 0, "components_kept": 0}
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(mesh.vertices_mm),
                                  o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)))
    labels, sizes, _ = m.cluster_connected_triangles()
    labels, sizes = np.asarray(labels), np.asarray(sizes)
    kept = np.flatnonzero(sizes >= min_fraction * sizes.max())
    tris = mesh.triangles[np.isin(labels, kept)]
    used = np.unique(tris)
    remap = np.full(len(mesh.vertices_mm), -1, np.int64)
    remap[used] = np.arange(len(used))
    cols = mesh.colors[used] if mesh.colors is not None else None
    facts = {"triangles_fused": len(mesh.triangles), "triangles_kept": len(tris),
             "components_fused": len(sizes), "components_kept": len(kept)}
    return Mesh(mesh.vertices_mm[used], remap[tris], cols), facts


def cleaning_warning(facts: dict) -> str | None:
    """A warning when cleaning dropped more than :data:`DROPPED_WARNING_FRACTION` of the
    fused triangles, else ``None``."""
    fused, kept = facts["triangles_fused"], facts["triangles_kept"]
    if fused and fused - kept > DROPPED_WARNING_FRACTION * fused:
        return (f"cleaning dropped {1 - kept / fused:.0%} of the fused triangles ({fused} -> {kept}; "
                f"{facts['components_kept']} of {facts['components_fused']} components kept): if the object has "
                "separate parts, lower mesh.min_component_fraction")
    return None


def depth_max_mm(world_to_cam: np.ndarray, norm_to_world: np.ndarray) -> float:
    """Farthest depth worth integrating: the far side of the scene sphere from any camera."""
    centre = norm_to_world[:3, 3]
    return float(max(np.linalg.norm(geometry.camera_center(T) - centre) for T in world_to_cam) + norm_to_world[0, 0])


def fuse_in_region(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, colors: np.ndarray | None,
                   norm_to_world: np.ndarray, cfg: MeshConfig, masks: np.ndarray | None) -> tuple[Mesh, np.ndarray, dict]:
    """What every mesher does with its depth maps: cut them to ``cfg.region`` (not when
    ``masks`` cut them under ``auto``: :func:`pipeline.meshing.region.cut_to_region`), fuse at
    ``cfg``'s sizes out to :func:`depth_max_mm`, drop the triangles outside the region, keep
    the components :func:`keep_components` keeps and close the holes up to
    ``cfg.fill_holes_norm`` that the depth maps support (:mod:`pipeline.meshing.holes`, with
    the truncation as tolerance). ``masks``: ``(M, H, W)`` bool of the first ``M`` views
    (the input views; their depth is already zero outside them), or ``None``. Returns the
    mesh (possibly empty), the depth maps fused and the facts (region, components, holes)."""
    depths, region, region_facts = bounding.cut_to_region(depths_mm, K, world_to_cam, norm_to_world, cfg,
                                                          masks is not None)
    voxel, trunc = cfg.sizes_mm(float(norm_to_world[0, 0]))
    mesh = fuse_depth_maps(depths, K, world_to_cam, colors, voxel, trunc, depth_max_mm(world_to_cam, norm_to_world))
    if region is not None:
        mesh.triangles = bounding.crop_mesh_vertices(mesh.vertices_mm, mesh.triangles, region)
    mesh, facts = keep_components(mesh, cfg.min_component_fraction)
    mesh.triangles, hole_facts = fill_supported_holes(mesh.vertices_mm, mesh.triangles, depths, K, world_to_cam, masks,
                                                      cfg.fill_holes_norm * float(norm_to_world[0, 0]), trunc)
    return mesh, depths, {**region_facts, **facts, **hole_facts}


def mesh_from_init(init_dir: str | Path, scene_dir: str | Path, cfg: MeshConfig) -> tuple[Mesh, dict]:
    """Fuse the init stage's depth maps of every view of ``scene_dir`` (cameras checked
    against the scene, colours from its images) and clean the mesh (world mm). Returns
    the mesh and facts: sizes, views, triangles fused and kept."""
    scene = load_scene(scene_dir, view_ids=None)
    depths = stacked_depths_mm(load_init_depths(init_dir, scene, needed_by="TSDF fusion"))
    mesh, _, facts = fuse_in_region(depths, scene.K, scene.world_to_cam, scene.images, scene.norm_to_world, cfg,
                                    masks=scene.masks)
    if len(mesh.triangles) == 0:
        raise FusionError(f"{init_dir}: the depth maps fuse into an empty mesh; nothing written")
    voxel, trunc = cfg.sizes_mm(scene.norm_scale_mm)
    info = {"voxel_mm": voxel, "trunc_mm": trunc, "depth_max_mm": depth_max_mm(scene.world_to_cam, scene.norm_to_world),
            "views": scene.view_ids, **facts, "vertices": len(mesh.vertices_mm),
            "min_component_fraction": cfg.min_component_fraction}
    return mesh, info


def write_mesh(path: str | Path, mesh: Mesh) -> None:
    """Binary PLY (float64 vertices, uchar colours, int32 faces), written atomically."""
    vertex = {"x": mesh.vertices_mm[:, 0], "y": mesh.vertices_mm[:, 1], "z": mesh.vertices_mm[:, 2]}
    if mesh.colors is not None:
        rgb = np.clip(np.round(mesh.colors * 255.0), 0, 255).astype(np.uint8)
        vertex.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    ply.write(path, vertex, faces=mesh.triangles)
