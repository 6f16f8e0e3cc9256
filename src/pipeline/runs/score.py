"""Per-scene metrics of the method (``reports/metrics/NAME.json``): DTU Chamfer of the mesh
where ground truth exists, else held-out-view mask IoU and masked PSNR (with the visual
hull's IoU as the reference); and what the training cost (from the optimize stage)."""
from __future__ import annotations

import json
from pathlib import Path

from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.data import dtu
from pipeline.data.heldout import load_heldout
from pipeline.evaluation import dtu_eval, gt, seen
from pipeline.evaluation.depth_error import depth_errors, gt_depths_mm
from pipeline.evaluation.heldout import heldout_scores
from pipeline.evaluation.record import MESH_KEYS, TIMING_KEYS, TRAIN_KEYS, Chamfer, HeldOut, SceneMetrics
from pipeline.meshing.raycast import MeshCaster
from pipeline.meshing.surfels import input_view_depths_mm
from pipeline.optimize.surfels import read_surfel_ply

HELDOUT_WIDTH = 200  # px; the bundled scan24 held-out views are stored at 200x150


def scene_metrics(name: str, scene_dir: str | Path, src_dir: str | Path, gt_dir: str | Path | None,
                  surfels_dir: str | Path, mesh_dir: str | Path, train_timing: str | Path,
                  eval_cfg: EvaluateConfig, opt_cfg: OptimizeConfig, mesh_cfg: MeshConfig, input_views: list[int],
                  backend: str = "cpu", log=print) -> SceneMetrics:
    scene_dir, surfels_dir, mesh_dir = Path(scene_dir), Path(surfels_dir), Path(mesh_dir)
    train = json.loads((surfels_dir / "train.json").read_text())
    timing = json.loads(Path(train_timing).read_text())
    mesh_facts = json.loads((mesh_dir / "mesh.json").read_text())
    common = {"scene": name, "train": {k: train[k] for k in TRAIN_KEYS}, "timing": {k: timing[k] for k in TIMING_KEYS},
              "mesh": {k: mesh_facts[k] for k in MESH_KEYS}}
    if gt_dir:
        scan_id = dtu.read_meta(scene_dir).get("scan_id")
        ground = gt.read_ground_truth(gt_dir, scan_id)
        cull = dtu_eval.load_cull_views(scene_dir, eval_cfg.cull_views, input_views)
        vertices, triangles = gt.read_mesh(mesh_dir / "mesh.ply")
        m = dtu_eval.evaluate_mesh(vertices, triangles, ground, eval_cfg, views=cull, log=log,
                                   name=str(mesh_dir / "mesh.ply"),
                                   seen_views=seen.load_input_views(scene_dir, input_views))
        return SceneMetrics(**common, chamfer=Chamfer.of(m),
                            input_depth_error=_input_depth_error(scene_dir, surfels_dir, ground.root / "mesh.ply",
                                                                 mesh_cfg, backend))
    else:
        scene = dtu.load_scene(scene_dir, view_ids=None)
        heldout = load_heldout(src_dir, scene.view_ids, HELDOUT_WIDTH)
        params = read_surfel_ply(surfels_dir / "surfels.ply", scene.norm_to_world)
    mesh = MeshCaster(*gt.read_mesh(mesh_dir / "mesh.ply"))
    h = heldout_scores(params, scene, heldout, background=opt_cfg.background, backend=backend, mesh=mesh)
    return SceneMetrics(**common, heldout=HeldOut.parse(h, f"{name}: held-out scores"))


def _input_depth_error(scene_dir: Path, surfels_dir: Path, gt_mesh: Path, mesh_cfg: MeshConfig,
                       backend: str) -> dict | None:
    """:func:`~pipeline.evaluation.depth_error.depth_errors` of the depth the mesh stage fuses
    (rendered at the input views as ``mesh_cfg`` says) against the GT mesh's; ``None``
    without a GT mesh (a real scan's official ground truth)."""
    if not gt_mesh.is_file():
        return None
    scene = dtu.load_scene(scene_dir)
    params = read_surfel_ply(surfels_dir / "surfels.ply", scene.norm_to_world)
    depths, _, masks = input_view_depths_mm(params, scene, mesh_cfg, backend)
    truth = gt_depths_mm(*gt.read_mesh(gt_mesh), scene.K, scene.world_to_cam, scene.width, scene.height)
    return depth_errors(depths, truth, masks)
