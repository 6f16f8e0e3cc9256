"""The mesh stage from files to files: trained surfels -> a gcgs ``mesh`` folder
(``mesh.ply``, world mm, and ``mesh.json``; docs/optimize.md)."""
from __future__ import annotations

import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.mesh import MeshConfig
from pipeline.data.dtu import load_scene
from pipeline.data.scene import check_made_from
from pipeline.meshing import tsdf
from pipeline.meshing.surfels import mesh_from_surfels
from pipeline.optimize.surfels import read_surfel_ply


def mesh_surfels_dir(scene_dir: str | Path, surfels_dir: str | Path, out_dir: str | Path, cfg: MeshConfig,
                     backend: str = "cpu") -> dict:
    """Files to files: ``surfels_dir/surfels.ply`` of the scene -> ``out_dir/mesh.ply`` and
    ``mesh.json`` (the facts, returned), the folder written atomically."""
    with atomic.atomic_dir(Path(out_dir), "mesh", inputs=(scene_dir, surfels_dir)) as tmp:
        scene = load_scene(scene_dir, view_ids=None)
        check_made_from(scene, surfels_dir, "train.json", "optimize")
        surfels = read_surfel_ply(Path(surfels_dir) / "surfels.ply", scene.norm_to_world)
        mesh, info = mesh_from_surfels(surfels, scene, cfg, backend)
        tsdf.write_mesh(tmp / "mesh.ply", mesh)
        (tmp / "mesh.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")
    return info
