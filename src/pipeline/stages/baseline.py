"""``gcgs baseline``: the classical baseline of one scene (docs/init.md): every init
backend's cloud and the MVS + TSDF mesh against the scene's ground truth, each step timed
(:mod:`pipeline.runs.baseline`). Reads the init stage's output for the default
backend; writes the other clouds, the mesh and its metrics to ``--out-dir`` and the
figures to ``--report`` (JSON). ``gcgs baseline-report`` combines the scenes' reports.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from pipeline import atomic
from pipeline.config.evaluate import EvaluateConfig
from pipeline.config.init import InitConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.params import load_params, section
from pipeline.config.scenes import scene_entry
from pipeline.measure import provenance
from pipeline.runs import baseline


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="scene name in params `scenes` (its ground truth: `gt`)")
    p.add_argument("--scene-dir", default=None, help="prepared scene (default: data/scenes/SCENE)")
    p.add_argument("--init-dir", default=None, help="the init stage's output (default: data/init/SCENE)")
    p.add_argument("--out-dir", default=None, help="clouds, mesh and metrics (default: data/baseline/SCENE)")
    p.add_argument("--init-metrics", default=None,
                   help="the init stage's time and memory (default: reports/init/SCENE.json, if present)")
    p.add_argument("--report", default=None, help="report JSON (default: reports/baseline/SCENE.json)")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    eval_cfg = section(EvaluateConfig, "evaluate", params)
    init_cfg = section(InitConfig, "init", params)
    entry = scene_entry(params, args.scene)
    name = args.scene
    out = Path(args.report or f"reports/baseline/{name}.json")
    scene_dir, init_dir = args.scene_dir or f"data/scenes/{name}", args.init_dir or f"data/init/{name}"
    atomic.check_output_file(out, inputs=(scene_dir, init_dir, entry.gt))  # before the work
    usage_path = Path(args.init_metrics or f"reports/init/{name}.json")
    init_usage = json.loads(usage_path.read_text()) if usage_path.is_file() else None
    report = baseline.baseline_scene(scene_dir, init_dir,
                                     args.out_dir or f"data/baseline/{name}", entry.gt, init_cfg, eval_cfg,
                                     section(MeshConfig, "mesh", params), init_usage,
                                     log=lambda m: print(f"[baseline] {name}: {m}", flush=True))
    report = {"scene": name, **provenance(), **report}
    atomic.write_text(out, json.dumps(report, indent=2) + "\n")
    print(f"[baseline] {name}: wrote {out}")
    failed = baseline.failed_steps(report)
    if failed:
        print(f"gcgs baseline: error: {name}: step(s) failed: {', '.join(failed)} (report: {out})")
    return 1 if failed else 0
