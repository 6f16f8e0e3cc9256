"""The 3-view limit from files to files: a synthetic scene -> its limit mesh in a gcgs
``limit`` folder and its Chamfer (docs/evaluation.md)."""
from __future__ import annotations

from pathlib import Path

from pipeline import atomic
from pipeline.config import EvaluateConfig
from pipeline.data.scene import SceneError
from pipeline.evaluation import gt
from pipeline.evaluation.limit import limit_chamfer, limit_mesh, mesh_area_mm2


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
