"""The mesh stage from files to files: trained surfels -> a gcgs ``mesh`` folder
(``mesh.ply``, world mm, and ``mesh.json``; docs/optimize.md)."""
from __future__ import annotations

import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.mesh import MeshConfig
from pipeline.data.dtu import load_scene
from pipeline.data.scene import check_made_from
from pipeline.errors import ConfigError
from pipeline.init.io import load_init_depths, stacked_depths_mm
from pipeline.meshing import tsdf
from pipeline.meshing.surfels import mesh_from_surfels
from pipeline.surfels import read_surfel_ply


def mesh_surfels_dir(scene_dir: str | Path, surfels_dir: str | Path, out_dir: str | Path, cfg: MeshConfig,
                     backend: str = "cpu", init_dir: str | Path | None = None) -> dict:
    """Files to files: ``surfels_dir/surfels.ply`` of the scene -> ``out_dir/mesh.ply`` and
    ``mesh.json`` (the facts, returned), the folder written atomically. ``init_dir``: the
    init stage's output, whose depth maps ``cfg.init_depth_rel_tol`` > 0 merges in (an
    error, before any work, when it is missing or has none)."""
    if cfg.init_depth_rel_tol > 0 and init_dir is None:
        raise ConfigError("mesh.init_depth_rel_tol > 0 merges the init's MVS depth maps: give the init folder "
                          "(gcgs mesh --init-dir), or set it to 0")
    inputs = (scene_dir, surfels_dir) + ((init_dir,) if init_dir is not None else ())
    with atomic.atomic_dir(Path(out_dir), "mesh", inputs=inputs) as tmp:
        scene = load_scene(scene_dir, view_ids=None)
        check_made_from(scene, surfels_dir, "train.json", "optimize")
        surfels = read_surfel_ply(Path(surfels_dir) / "surfels.ply", scene.norm_to_world)
        init_depths = None
        if cfg.init_depth_rel_tol > 0:
            init_depths = stacked_depths_mm(load_init_depths(init_dir, scene, needed_by="mesh.init_depth_rel_tol"))
        mesh, info = mesh_from_surfels(surfels, scene, cfg, backend, init_depths)
        tsdf.write_mesh(tmp / "mesh.ply", mesh)
        (tmp / "mesh.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")
    return info
