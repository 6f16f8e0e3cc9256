"""The init stage from files to files: a prepared scene -> ``points.ply``, depth maps and
``init.json`` in a gcgs ``init`` folder (docs/init.md)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from pipeline.atomic import atomic_dir
from pipeline.config.init import InitConfig
from pipeline.data.dtu import load_scene
from pipeline.data.scene import SceneError, check_scene
from pipeline.init.backends import run_backend
from pipeline.init.io import InitResult, depth_path, write_depth, write_ply


def write_outputs(folder: Path, result: InitResult, info: dict) -> None:
    """Write points.ply, depth maps and init.json into ``folder`` (an atomic temporary one)."""
    write_ply(folder / "points.ply", result.cloud)
    for d in result.depths or []:
        write_depth(depth_path(folder, d.view_id), d)
    (folder / "init.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")


def run_init(scene_dir: str | Path, out_dir: str | Path, cfg: InitConfig) -> tuple[InitResult, dict]:
    """Load the scene, run ``cfg.backend`` and write the outputs (a gcgs ``init`` folder,
    claimed before the work); returns the result and the facts written to init.json (no
    timings: identical inputs give identical bytes)."""
    with atomic_dir(out_dir, "init", inputs=(scene_dir, cfg.mast3r.model or None)) as tmp:
        scene = load_scene(scene_dir, view_ids=None)
        check_scene(scene, min_views=2, needed_by="init")
        result = run_backend(cfg.backend, scene, cfg)
        if len(result.cloud) == 0:
            raise SceneError(f"{scene_dir}: the {cfg.backend} backend found no points; nothing written to {out_dir}")
        info = {
            "scene": str(scene_dir),
            "scene_fingerprint": scene.fingerprint(),
            "backend": cfg.backend,
            "views": scene.view_ids,
            "size": [scene.width, scene.height],
            "num_points": len(result.cloud),
            "config": dataclasses.asdict(cfg),
            **result.info,
        }
        write_outputs(tmp, result, info)
    return result, info
