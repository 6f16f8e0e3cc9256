"""The 3-view limit from files to files: a synthetic scene -> its limit mesh and its exact-depth
mesh (the meshing fed exact depth) in a gcgs ``limit`` folder, and their Chamfer
(docs/evaluation.md)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import atomic
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.mesh import MeshConfig
from pipeline.data import dtu
from pipeline.data.scene import SceneError
from pipeline.evaluation import dtu_eval, gt, seen
from pipeline.evaluation.record import SPLITS
from pipeline.synth.limit import exact_depth_mesh, limit_mesh, mesh_area_mm2


def limit_chamfer(mesh: tuple[np.ndarray, np.ndarray], scene_dir: str | Path, ground: gt.GroundTruth,
                  cfg: EvaluateConfig, views: list[int], log=None, name: str = "3-view limit") -> dict:
    """DTU Chamfer of a yardstick mesh against the scene's GT (:func:`pipeline.evaluation.gt.
    read_ground_truth`), culled like the method's mesh (``evaluate.cull_views`` of the prepared
    ``scene_dir``)."""
    cull = dtu_eval.load_cull_views(scene_dir, cfg.cull_views, views)
    m = dtu_eval.evaluate_mesh(mesh[0], mesh[1], ground, cfg, views=cull, log=log, name=name,
                               seen_views=seen.load_input_views(scene_dir, views))
    return {k: m[k] for k in ("accuracy_mm", "completeness_mm", "overall_mm", "valid", "problems", "counts", *SPLITS)}


def run_limit(synth_dir: str | Path, scene_dir: str | Path, out_dir: str | Path, cfg: EvaluateConfig,
              mesh_cfg: MeshConfig, views: list[int], log=None) -> dict:
    """Files to files: the limit mesh of ``synth_dir`` for ``views`` -> ``out_dir/mesh.ply`` and
    the exact-depth mesh of the prepared ``scene_dir`` (its input views, size and masks) ->
    ``out_dir/exact_depth_mesh.ply`` (a gcgs ``limit`` output); returns both Chamfers
    (``chamfer``, ``exact_depth``) and the share of the GT area the limit keeps."""
    synth_dir = Path(synth_dir)
    with atomic.atomic_dir(out_dir, "limit", inputs=(synth_dir, scene_dir)) as tmp:
        V, F = limit_mesh(synth_dir, views)
        if len(F) == 0:
            raise SceneError(f"{synth_dir}: the input views {views} see no ground-truth triangle")
        gt_mesh = gt.read_mesh(gt.paths(synth_dir / "gt", 0)["mesh"])
        gt.write_ply_mesh(tmp / "mesh.ply", V, F)
        ground = gt.read_ground_truth(synth_dir / "gt", dtu.read_meta(Path(scene_dir)).get("scan_id"))
        chamfer = limit_chamfer((V, F), scene_dir, ground, cfg, views, log)
        scene = dtu.load_scene(scene_dir, view_ids=views)
        exact = exact_depth_mesh(*gt_mesh, scene, mesh_cfg)
        gt.write_ply_mesh(tmp / "exact_depth_mesh.ply", exact.vertices_mm, exact.triangles)
        exact_chamfer = limit_chamfer((exact.vertices_mm, exact.triangles), scene_dir, ground, cfg, views,
                                      log, name="exact depth through the same meshing")
    return {"views": list(views), "chamfer": chamfer, "exact_depth": exact_chamfer,
            "gt_area_seen_fraction": round(mesh_area_mm2(V, F) / mesh_area_mm2(*gt_mesh), 4)}
