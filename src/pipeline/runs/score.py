"""Per-scene metrics of the method (``reports/metrics/NAME.json``): DTU Chamfer of the mesh
where ground truth exists, else held-out-view mask IoU and masked PSNR (with the visual
hull's IoU as the reference); and what the training cost (from the optimize stage)."""
from __future__ import annotations

from pathlib import Path

from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.data import dtu
from pipeline.data.heldout import load_heldout
from pipeline.evaluation import dtu_eval, gt, seen
from pipeline.evaluation.depth_error import depth_errors, gt_depths_mm
from pipeline.evaluation.heldout import heldout_scores
from pipeline.evaluation.record import MESH_KEYS, TIMING_KEYS, TRAIN_KEYS, Chamfer, HeldOut, MetricsError, SceneMetrics
from pipeline.meshing.surfels import input_view_depths_mm
from pipeline.raycast import MeshCaster
from pipeline.jsonfile import read_json
from pipeline.surfels import read_surfel_ply

HELDOUT_WIDTH = 200  # px; the bundled scan24 held-out views are stored at 200x150


def scene_metrics(name: str, scene_dir: str | Path, src_dir: str | Path, gt_dir: str | Path | None,
                  surfels_dir: str | Path, mesh_dir: str | Path, train_timing: str | Path,
                  eval_cfg: EvaluateConfig, opt_cfg: OptimizeConfig, mesh_cfg: MeshConfig, input_views: list[int],
                  backend: str = "cpu", log=print) -> SceneMetrics:
    scene_dir, surfels_dir, mesh_dir = Path(scene_dir), Path(surfels_dir), Path(mesh_dir)
    common = {"scene": name,
              "train": _facts(surfels_dir / "train.json", "training facts", TRAIN_KEYS, "gcgs optimize"),
              "timing": _facts(Path(train_timing), "training timings", TIMING_KEYS, "gcgs optimize"),
              "mesh": _facts(mesh_dir / "mesh.json", "mesh facts", MESH_KEYS, "gcgs mesh")}
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


def _facts(path: Path, what: str, keys: tuple[str, ...], made_by: str) -> dict:
    """``keys`` of the JSON object at ``path``, which ``made_by`` writes."""
    data = read_json(path, what, f"written by `{made_by}`")
    missing = [k for k in keys if k not in data]
    if missing:
        raise MetricsError(f"{path}: {what} lack {', '.join(f'`{k}`' for k in missing)}")
    return {k: data[k] for k in keys}


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
