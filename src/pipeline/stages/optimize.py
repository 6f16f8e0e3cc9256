"""``gcgs optimize``: train 2D Gaussian surfels on a prepared scene (docs/optimize.md).

Writes ``OUT/surfels.ply`` (2DGS attribute layout, world frame, mm) and ``OUT/train.json``
(what was trained: counts, final loss terms; no timings, so two runs give the same bytes).
Timings, peak memory and the time split go to ``--metrics`` (JSON), the training curves to
``--live-dir`` (dvclive). A checkpoint in ``--checkpoint`` (outside the DVC output, which
DVC deletes before a run) lets an interrupted run resume.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict
from pathlib import Path

from pipeline import atomic
from pipeline.config import LossConfig, OptimizeConfig, load_params, section
from pipeline.data.dtu import load_scene
from pipeline.init.io import read_ply
from pipeline.measure import peak_rss_mb
from pipeline.optimize import init_from_cloud, make_views, train, uses_masks
from pipeline.optimize.surfels import write_surfel_ply


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", required=True, help="prepared scene folder")
    p.add_argument("--init-dir", required=True, help="init stage output (points.ply)")
    p.add_argument("--priors-dir", required=True, help="priors stage output (normals/, features/)")
    p.add_argument("--out-dir", required=True, help="writes surfels.ply and train.json")
    p.add_argument("--checkpoint", default=None, help="checkpoint file (default: data/checkpoints/NAME.pt)")
    p.add_argument("--metrics", default=None, help="timings JSON (default: reports/train/NAME.json)")
    p.add_argument("--live-dir", default=None, help="dvclive folder (default: reports/train/NAME)")
    p.add_argument("--iterations", type=int, default=None, help="default: optimize.iterations")
    p.add_argument("--backend", choices=OptimizeConfig.BACKENDS, default=None, help="default: optimize.backend")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    cfg = section(OptimizeConfig, "optimize", params, {"iterations": args.iterations, "backend": args.backend})
    loss = section(LossConfig, "loss", params)
    out_dir = Path(args.out_dir)
    name = out_dir.name
    ckpt = Path(args.checkpoint or f"data/checkpoints/{name}.pt")
    metrics_path = Path(args.metrics or f"reports/train/{name}.json")
    live_dir = Path(args.live_dir or f"reports/train/{name}")

    t0, c0 = time.perf_counter(), time.process_time()
    scene = load_scene(args.scene, view_ids=None)
    cloud = read_ply(Path(args.init_dir) / "points.ply")
    surfels = init_from_cloud(cloud, scene, cfg, where=str(Path(args.init_dir) / "points.ply"))
    views = make_views(scene, args.priors_dir, cfg, loss)

    from dvclive import Live

    live = Live(str(live_dir), save_dvc_exp=False, dvcyaml=None, report=None)

    def on_log(row: dict) -> None:
        live.step = row["iteration"]
        for k in ("total", "l1", "photo", "gcf", "nor", "dn", "dist", "mask", "surfels", "seconds"):
            if k in row:
                live.log_metric(f"train/{k}", row[k], plot=True)

    ckpt.parent.mkdir(parents=True, exist_ok=True)
    result = train(surfels, views, cfg, loss, checkpoint=ckpt, on_log=on_log, progress=not args.no_progress)
    live.end()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0

    facts = {
        "scene": str(args.scene), "preset": cfg.preset, "backend": result.backend, "iterations": result.iterations,
        "surfels_init": result.num_init, "surfels_final": result.params.num,
        "removed_degenerate": result.removed_degenerate, "masks": uses_masks(scene, cfg),
        "final_terms": {k: round(v, 6) for k, v in result.final_terms.items() if isinstance(v, float)},
        "frame": "surfels.ply: world frame, mm (training ran in the normalised frame)",
        "config": asdict(cfg), "loss": asdict(loss),
    }
    with atomic.atomic_dir(out_dir) as tmp:
        write_surfel_ply(tmp / "surfels.ply", result.params, scene.norm_to_world)
        (tmp / "train.json").write_text(json.dumps(facts, indent=2, sort_keys=True) + "\n")
    iters_run = result.iterations - (result.resumed_from or 0)
    timing = {
        "wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "peak_rss_mb": peak_rss_mb(),
        "iterations": result.iterations, "iterations_this_run": iters_run, "resumed_from": result.resumed_from,
        "s_per_iteration": round(sum(result.seconds.values()) / max(iters_run, 1), 4),
        "split_s": {k: round(v, 3) for k, v in result.seconds.items()},
        "surfels_final": result.params.num, "backend": result.backend, "preset": cfg.preset,
    }
    metrics_path.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_text(metrics_path, json.dumps(timing, indent=2) + "\n")
    ckpt.unlink(missing_ok=True)  # finished: the output is the state now
    print(f"optimize {name}: {result.iterations} iterations ({cfg.preset}, {result.backend}) in {wall:.0f} s, "
          f"{result.num_init} -> {result.params.num} surfels -> {out_dir}")
    return 0
