"""``gcgs init``: the initial point cloud of a prepared scene (docs/init.md).

Writes ``OUT/points.ply``, ``OUT/depth/{view:03d}.npz`` (depth backends) and
``OUT/init.json``, all into a temporary sibling folder renamed into place at the end.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from pipeline import atomic
from pipeline.atomic import atomic_dir
from pipeline.config import InitConfig, load_params, section
from pipeline.data.dtu import load_scene
from pipeline.data.scene import SceneError, check_scene
from pipeline.init import match_summary, run_backend
from pipeline.init.io import InitResult, depth_path, write_depth, write_ply
from pipeline.measure import measure


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


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder (DTU layout)")
    p.add_argument("--backend", choices=InitConfig.BACKENDS, default=None, help="default: init.backend")
    p.add_argument("--model", default=None, help="ONNX model file (mast3r backend); default: init.mast3r.model")
    p.add_argument("--out-dir", required=True, help="output folder (points.ply, depth/, init.json)")
    p.add_argument("--metrics", default=None, help="also write the run's time and peak memory to this JSON")
    p.add_argument("--params", default=None, help="params.yaml to read `init` from (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    cfg = section(InitConfig, "init", load_params(args.params), {"backend": args.backend, "mast3r.model": args.model})
    if args.metrics:
        atomic.check_output_file(args.metrics)
    with measure(reset_peak=False) as usage:
        _, info = run_init(args.scene, args.out_dir, cfg)
    print(f"init {cfg.backend}: {info['num_points']} points in {usage.wall_s:.2f} s "
          f"(peak RSS {usage.peak_rss_mb} MB) -> {args.out_dir}", *match_summary(info), sep="\n")
    if args.metrics:  # timings live here, not in the output (same inputs, same bytes)
        atomic.write_text(args.metrics, json.dumps({"backend": cfg.backend, **usage.as_dict()}, indent=2) + "\n")
    return 0
