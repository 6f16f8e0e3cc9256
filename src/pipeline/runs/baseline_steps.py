"""The steps of the baseline (:mod:`pipeline.runs.baseline`) that run in a child
process each. A child imports this module: its imports are inside each step so that a
child's peak memory holds what its step needs, as a ``gcgs`` command's would, not the
imports of every step."""
from __future__ import annotations

from pathlib import Path

from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.init import InitConfig
from pipeline.config.mesh import MeshConfig


def backend_cloud(scene_dir: Path, backend: str, cfg: InitConfig, out_ply: Path) -> dict:
    """Run init ``backend`` on the scene and write its cloud, with an ``init.json`` beside it
    that names the scene (so a training on it can check it); returns its facts."""
    import json

    from pipeline.data import dtu
    from pipeline.data.scene import SceneError
    from pipeline.init.backends import run_backend
    from pipeline.init.io import write_ply

    scene = dtu.load_scene(scene_dir, view_ids=None)
    result = run_backend(backend, scene, cfg)
    if len(result.cloud) == 0:
        raise SceneError(f"{scene_dir}: the {backend} backend found no points")
    write_ply(out_ply, result.cloud)
    facts = {"backend": backend, "num_points": len(result.cloud), **result.info}
    (out_ply.parent / "init.json").write_text(json.dumps(
        {"scene": str(scene_dir), "scene_fingerprint": scene.fingerprint(), **facts}, indent=2, sort_keys=True) + "\n")
    return facts


def tsdf_mesh(init_dir: Path, scene_dir: Path, cfg: MeshConfig, out_ply: Path) -> dict:
    """TSDF-fuse the init folder's depth maps and write the mesh; returns its facts."""
    from pipeline.meshing import tsdf

    mesh, info = tsdf.mesh_from_init(init_dir, scene_dir, cfg)
    tsdf.write_mesh(out_ply, mesh)
    return info


def mesh_chamfer(mesh_ply: Path, scene_dir: Path, gt_dir: Path, cfg: EvaluateConfig, views: list[int],
                 out_json: Path) -> None:
    """DTU Chamfer distance of the mesh, culled by ``views``' masks, written to ``out_json``
    (``mesh``: the mesh file's name, in the JSON's folder: the folder is written under a
    temporary name, which must not end up in the output)."""
    from pipeline.data import dtu
    from pipeline.evaluation import dtu_eval, gt, seen

    ground = gt.read_ground_truth(gt_dir, dtu.read_meta(Path(scene_dir)).get("scan_id"))
    cull = dtu_eval.load_cull_views(scene_dir, cfg.cull_views, views)
    vertices, triangles = gt.read_mesh(mesh_ply)
    metrics = dtu_eval.evaluate_mesh(vertices, triangles, ground, cfg, views=cull, log=None, name=str(mesh_ply),
                                     seen_views=seen.load_input_views(scene_dir, views))
    dtu_eval.write_metrics(out_json, {**metrics, "mesh": mesh_ply.name, "scene": str(scene_dir), "gt": str(ground.root)})
