"""Mesh from trained surfels: render depth at the input views (and optional virtual views
between them), fuse by TSDF in mm (docs/mesh.md).

Frames and units: surfels live in the normalised frame (``pipeline.surfels``);
rendered depth is normalised camera z, multiplied by the scale_mat radius to mm; fusion
runs in the world frame in mm with the scene's world-to-camera transforms.
"""
from __future__ import annotations

import numpy as np
import torch

from pipeline import geometry
from pipeline.config.mesh import MeshConfig
from pipeline.data.scene import Scene
from pipeline.meshing import tsdf
from pipeline.rasterizer import Camera, rasterize
from pipeline.surfels import SurfelParams


def virtual_world_to_cams(world_to_cam: np.ndarray, centre_mm: np.ndarray, per_pair: int) -> np.ndarray:
    """Cameras between each pair of input cameras: centres on the arc around ``centre_mm``
    (spherical interpolation of the direction, linear in distance), each looking at
    ``centre_mm`` with its image "down" axis from the slerp of the pair's orientations;
    ``per_pair`` views strictly between each pair. ``(M, 4, 4)`` world mm -> camera."""
    from scipy.spatial.transform import Rotation, Slerp

    out = []
    n = len(world_to_cam)
    for a in range(n):
        for b in range(a + 1, n):
            ca, cb = geometry.camera_center(world_to_cam[a]) - centre_mm, geometry.camera_center(world_to_cam[b]) - centre_mm
            ra, rb = np.linalg.norm(ca), np.linalg.norm(cb)
            slerp = Slerp([0.0, 1.0], Rotation.from_matrix([world_to_cam[a][:3, :3], world_to_cam[b][:3, :3]]))
            omega = np.arccos(np.clip(ca @ cb / (ra * rb), -1.0, 1.0))
            for k in range(1, per_pair + 1):
                t = k / (per_pair + 1)
                if omega < 1e-9:
                    d = ca / ra
                else:
                    d = (np.sin((1 - t) * omega) * ca / ra + np.sin(t * omega) * cb / rb) / np.sin(omega)
                c = centre_mm + d * ((1 - t) * ra + t * rb)
                z = -d  # forward: towards the centre
                y = slerp([t]).as_matrix()[0][1]
                y = y - (y @ z) * z
                y /= np.linalg.norm(y)
                R = np.stack([np.cross(y, z), y, z])
                T = np.eye(4)
                T[:3, :3] = R
                T[:3, 3] = -R @ c
                out.append(T)
    return np.stack(out) if out else np.zeros((0, 4, 4))


@torch.no_grad()
def render_depths_mm(params: SurfelParams, scene: Scene, world_to_cam_mm: np.ndarray, K: np.ndarray, width: int,
                     height: int, depth: str = "median", alpha_min: float = 0.5, backend: str = "cpu",
                     masks: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render ``(N, H, W)`` depth (camera z, mm; 0 = no depth) and colour at each camera.

    A pixel has depth where the accumulated alpha exceeds ``alpha_min`` (and, when ``masks``
    is given, inside the mask)."""
    s = scene.norm_scale_mm
    S = scene.norm_to_world
    surf = params.surfels(params.sh_degree_max)
    depths, colors = [], []
    for i, T in enumerate(world_to_cam_mm):
        T_norm = T @ S
        T_norm[:3, :] /= s
        T_norm[3] = [0.0, 0.0, 0.0, 1.0]
        out = rasterize(surf, Camera(K[i], T_norm, width, height), backend)
        d = (out.depth_median if depth == "median" else out.depth_expected).double().numpy() * s
        ok = (out.alpha.double().numpy() > alpha_min) & (d > 0)
        if masks is not None:
            ok &= masks[i]
        depths.append(np.where(ok, d, 0.0))
        colors.append(out.features.clamp(0, 1).double().numpy())
    return np.stack(depths), np.stack(colors)


def input_view_depths_mm(params: SurfelParams, scene: Scene, cfg: MeshConfig,
                         backend: str = "cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """What the mesh stage fuses at the input views: ``(depths, colours, masks)`` of
    :func:`render_depths_mm` with ``cfg.depth`` and ``cfg.alpha_min``, masked by the scene's
    masks when ``cfg.masks`` and it has them (``masks``: those masks, else ``None``)."""
    masks = tsdf.fusion_masks(scene, cfg)
    depths, colours = render_depths_mm(params, scene, scene.world_to_cam, scene.K, scene.width, scene.height,
                                       cfg.depth, cfg.alpha_min, backend, masks)
    return depths, colours, masks


def merge_init_depth(rendered_mm: np.ndarray, init_mm: np.ndarray, rel_tol: float) -> tuple[np.ndarray, int]:
    """``rendered_mm`` with each pixel where ``init_mm`` has a depth within ``rel_tol`` of it
    (``|init - rendered| < rel_tol x init``; 0 = no depth in either) taken from ``init_mm``.
    Why: where the init's two-view-confirmed MVS depth and the trained surfels agree, the
    MVS depth (matched at full resolution) is the more accurate of the two; where they
    disagree or the init has none, the surfels' depth stands. Returns the merged maps and
    how many pixels came from ``init_mm``."""
    if rendered_mm.shape != init_mm.shape:
        raise ValueError(f"merge_init_depth: rendered {rendered_mm.shape} and init {init_mm.shape} depth maps differ in shape")
    both = (rendered_mm > 0) & (init_mm > 0)
    agree = both & (np.abs(init_mm - rendered_mm) < rel_tol * np.where(both, init_mm, 1.0))
    return np.where(agree, init_mm, rendered_mm), int(agree.sum())


def mesh_from_surfels(params: SurfelParams, scene: Scene, cfg: MeshConfig, backend: str = "cpu",
                      init_depths_mm: np.ndarray | None = None) -> tuple[tsdf.Mesh, dict]:
    """Cleaned TSDF mesh (world mm) of surfels rendered at every input view (masked when
    ``cfg.masks`` and the scene has masks) and ``cfg.virtual_per_pair`` virtual views between
    each pair of input views (unmasked: no mask exists there). With ``cfg.init_depth_rel_tol``
    the input views' depth is merged with ``init_depths_mm`` (``(N, H, W)`` camera z, mm, 0 =
    none: the init stage's MVS depth maps) first (:func:`merge_init_depth`). Returns the mesh
    and facts."""
    d_in, c_in, masks = input_view_depths_mm(params, scene, cfg, backend)
    from_init = 0
    if cfg.init_depth_rel_tol > 0:
        if init_depths_mm is None:
            raise ValueError("mesh_from_surfels: mesh.init_depth_rel_tol > 0 needs the init's depth maps")
        d_in, from_init = merge_init_depth(d_in, init_depths_mm, cfg.init_depth_rel_tol)
    Ts, Ks, ds, cs = [scene.world_to_cam], [scene.K], [d_in], [c_in]
    if cfg.virtual_per_pair > 0:
        T_v = virtual_world_to_cams(scene.world_to_cam, scene.norm_to_world[:3, 3], cfg.virtual_per_pair)
        K_v = np.repeat(scene.K[:1], len(T_v), axis=0)
        d_v, c_v = render_depths_mm(params, scene, T_v, K_v, scene.width, scene.height, cfg.depth, cfg.alpha_min,
                                    backend)
        Ts, Ks, ds, cs = Ts + [T_v], Ks + [K_v], ds + [d_v], cs + [c_v]
    Ts, Ks, ds, cs = (np.concatenate(x) for x in (Ts, Ks, ds, cs))
    if not (ds > 0).any():
        raise tsdf.FusionError(f"{scene.source}: the surfels render no depth above alpha {cfg.alpha_min} in any view "
                               "(an empty or transparent model: did training fail?)")
    mesh, fused, facts = tsdf.fuse_in_region(ds, Ks, Ts, cs, scene.norm_to_world, cfg, masks=masks)
    if len(mesh.triangles) == 0:
        raise tsdf.FusionError(f"{scene.source}: the surfels' rendered depth fuses into an empty mesh; nothing written")
    voxel, trunc = cfg.sizes_mm(scene.norm_scale_mm)
    info = {"views_input": scene.num_views, "views_virtual": len(Ts) - scene.num_views, "depth": cfg.depth,
            "depth_pixels": int((fused > 0).sum()), "depth_pixels_from_init": from_init, "voxel_mm": voxel, "trunc_mm": trunc, "masks": masks is not None,
            **facts, "vertices": len(mesh.vertices_mm)}
    return mesh, info
