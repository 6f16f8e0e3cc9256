"""The 3-view limit of a synthetic scene: what a method that reconstructs exactly what the
input views see, and invents nothing, would score.

Its mesh is the scene's ground-truth surface cut down to the triangles the input views see,
by the rule that made the ground truth from all 49 views (:func:`pipeline.synth.scenes.
visible_gt_mesh`: centroid inside the image, face turned to the camera, nothing of the
scene, object or table, in front of it); it is scored like any other mesh (DTU Chamfer with
the method's culling). Accuracy is then near zero (only the DTU sampling and the cut
triangles' edges) and completeness is what the unseen surface costs: a row of Table II that
loses to this one loses on the side that shows it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.config import EvaluateConfig
from pipeline.data import dtu
from pipeline.data.scene import SceneError
from pipeline.evaluation import dtu_eval, gt


def limit_mesh(synth_dir: str | Path, views: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The ground truth of the synthetic scene in ``synth_dir`` (``gcgs synth`` output) seen
    by ``views``: ``(vertices (V, 3) world mm, triangles (F, 3))``."""
    from pipeline.synth.render import Renderer
    from pipeline.synth.scenes import build_scene, visible_gt_mesh

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


def limit_chamfer(mesh: tuple[np.ndarray, np.ndarray], scene_dir: str | Path, gt_dir: str | Path, cfg: EvaluateConfig,
                  views: list[int], log=None) -> dict:
    """DTU Chamfer of the limit mesh against the scene's GT, culled like the method's mesh
    (``evaluate.cull_views`` of the prepared ``scene_dir``)."""
    ground = gt.read_ground_truth(gt_dir, dtu.read_meta(Path(scene_dir)).get("scan_id"))
    cull = dtu_eval.load_cull_views(scene_dir, cfg.cull_views, views)
    m = dtu_eval.evaluate_mesh(mesh[0], mesh[1], ground, cfg, views=cull, log=log,
                               name="3-view limit")
    return {k: m[k] for k in ("accuracy_mm", "completeness_mm", "overall_mm", "valid", "problems", "counts")}


def mesh_area_mm2(vertices: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    return float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum() / 2)
