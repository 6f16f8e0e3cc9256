"""The 3-view limit's mesh: a synthetic scene's ground truth cut down to the triangles the
input views see, by the rule that made the ground truth from all 49 views
(:func:`pipeline.synth.scenes.visible_gt_mesh`: centroid inside the image, face turned to the
camera, nothing of the scene, object or table, in front of it). Scored like any mesh it is
what a method that reconstructs exactly what the input views see, and invents nothing,
would score (:mod:`pipeline.runs.limit`, docs/evaluation.md).

Beside it, :func:`exact_depth_mesh`: the mesh stage's meshing fed the exact depth of the
input views, what the method would score if its rendered depth were perfect. The gap from
the limit to it is what the meshing costs; the gap from it to the method is what training
costs.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.config.mesh import MeshConfig
from pipeline.data import dtu
from pipeline.data.scene import Scene, SceneError
from pipeline.evaluation.depth_error import gt_depths_mm
from pipeline.meshing import tsdf
from pipeline.synth.render import Renderer
from pipeline.synth.scenes import build_scene, visible_gt_mesh


def limit_mesh(synth_dir: str | Path, views: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth of the synthetic scene in ``synth_dir`` (``gcgs synth`` output) seen
    by ``views``: ``(vertices (V, 3) world mm, triangles (F, 3))``."""
    synth_dir = Path(synth_dir)
    meta = dtu.read_meta(synth_dir)
    if meta.get("source") != "synthetic" or "name" not in meta or "seed" not in meta:
        raise SceneError(f"{synth_dir / 'scene.json'}: not a synthetic scene written by `gcgs synth` "
                         "(the 3-view limit needs its exact geometry)")
    cams = dtu.load_cameras(synth_dir)
    missing = [v for v in views if v not in cams.K]
    if missing:
        raise SceneError(f"{cams.path}: no camera for input view(s) {missing}")
    scene = build_scene(meta["name"], int(meta["seed"]), cams)
    inputs = dtu.DTUCameras(K={v: cams.K[v] for v in views}, world_to_cam={v: cams.world_to_cam[v] for v in views},
                            norm_to_world=cams.norm_to_world, path=cams.path)
    V, F = visible_gt_mesh(scene, Renderer(scene), inputs, dtu.stored_image_size(synth_dir))
    return scene.to_world(V), F


def mesh_area_mm2(vertices: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    return float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2)


def exact_depth_mesh(gt_vertices_mm: np.ndarray, gt_triangles: np.ndarray, scene: Scene,
                     cfg: MeshConfig) -> tsdf.Mesh:
    """The mesh stage's TSDF meshing (:func:`pipeline.meshing.tsdf.fuse_in_region` at ``cfg``'s
    sizes, region and component rules) of the GT mesh's exact depth (camera z, mm, through
    the integer pixel centres) at ``scene``'s input views and image size, masked by the
    scene's masks as the mesh stage masks rendered depth (``cfg.masks``)."""
    masks = tsdf.fusion_masks(scene, cfg)
    depths = gt_depths_mm(gt_vertices_mm, gt_triangles, scene.K, scene.world_to_cam, scene.width, scene.height)
    if masks is not None:
        depths = np.where(masks, depths, 0.0)
    if not (depths > 0).any():
        raise SceneError(f"{scene.source}: the ground truth covers no pixel of the input views")
    mesh, _, _ = tsdf.fuse_in_region(depths, scene.K, scene.world_to_cam, None, scene.norm_to_world, cfg,
                                     masks=masks)
    return mesh
