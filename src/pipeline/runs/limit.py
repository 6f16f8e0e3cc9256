"""The 3-view limit from files to files: a synthetic scene -> its limit mesh in a gcgs
``limit`` folder and its Chamfer (docs/evaluation.md)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline import atomic
from pipeline.config.evaluate import EvaluateConfig
from pipeline.data import dtu
from pipeline.data.scene import SceneError
from pipeline.evaluation import dtu_eval, gt, seen
from pipeline.synth.limit import limit_mesh, mesh_area_mm2


def limit_chamfer(mesh: tuple[np.ndarray, np.ndarray], scene_dir: str | Path, gt_dir: str | Path,
                  cfg: EvaluateConfig, views: list[int], log=None) -> dict:
    """DTU Chamfer of the limit mesh against the scene's GT, culled like the method's mesh
    (``evaluate.cull_views`` of the prepared ``scene_dir``)."""
    ground = gt.read_ground_truth(gt_dir, dtu.read_meta(Path(scene_dir)).get("scan_id"))
    cull = dtu_eval.load_cull_views(scene_dir, cfg.cull_views, views)
    m = dtu_eval.evaluate_mesh(mesh[0], mesh[1], ground, cfg, views=cull, log=log, name="3-view limit",
                               seen_views=seen.load_input_views(scene_dir, views))
    return {k: m[k] for k in ("accuracy_mm", "completeness_mm", "overall_mm", "valid", "problems", "counts",
                              "accuracy_by_views_seen", "completeness_by_views_seen")}


def run_limit(synth_dir: str | Path, scene_dir: str | Path, out_dir: str | Path, cfg: EvaluateConfig,
              views: list[int], log=None) -> dict:
    """Files to files: the limit mesh of ``synth_dir`` for ``views`` -> ``out_dir/mesh.ply``
    (a gcgs ``limit`` output); returns its Chamfer and the share of the GT area it keeps."""
    synth_dir = Path(synth_dir)
    with atomic.atomic_dir(out_dir, "limit", inputs=(synth_dir, scene_dir)) as tmp:
        V, F = limit_mesh(synth_dir, views)
        if len(F) == 0:
            raise SceneError(f"{synth_dir}: the input views {views} see no ground-truth triangle")
        gt_mesh = gt.read_mesh(gt.paths(synth_dir / "gt", 0)["mesh"])
        gt.write_ply_mesh(tmp / "mesh.ply", V, F)
        chamfer = limit_chamfer((V, F), scene_dir, synth_dir / "gt", cfg, views, log)
    return {"views": list(views), "chamfer": chamfer,
            "gt_area_seen_fraction": round(mesh_area_mm2(V, F) / mesh_area_mm2(*gt_mesh), 4)}
