"""``gcgs bench-priors``: time and peak memory of the priors stage and of the prior losses.

Needs a prepared scene and its init output (default: the bundled scan,
``dvc repro init@scan24``). Each stage configuration runs ``--repeats`` times as
``gcgs priors`` in a fresh child process (:func:`pipeline.measure.run_in_child`: wall time
and peak RSS of the whole process, Python, torch and onnxruntime imports included). Writes
``--out`` (JSON).
"""
from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch
import yaml

from pipeline import atomic, cli
from pipeline.config.params import load_params
from pipeline.measure import provenance, run_in_child

CONFIGS = {"normals+features (default)": {}, "normals only (lambda_gcf=0)": {"lambda_gcf": 0.0},
           "features only (lambda_nor=0)": {"lambda_nor": 0.0}}


def bench_stage(scene: str, init_dir: str, params: dict, repeats: int, tmp: Path) -> dict:
    out = {}
    for name, loss in CONFIGS.items():
        pfile = tmp / f"params_{len(out)}.yaml"
        pfile.write_text(yaml.safe_dump(dict(params, loss={**params["loss"], **loss})))
        argv = ["priors", "--scene", scene, "--init-dir", init_dir, "--out-dir", str(tmp / "out"), "--params", str(pfile)]
        runs = []
        for _ in range(repeats):
            rc, usage = run_in_child(cli.main, argv)
            if rc != 0:
                raise RuntimeError(f"gcgs {' '.join(argv)} exited with {rc}")
            runs.append(usage)
        out[name] = {"wall_s_median": round(statistics.median(r.wall_s for r in runs), 2),
                     "max_rss_mb_max": max(r.peak_rss_mb for r in runs),
                     "output_mb": round(sum(f.stat().st_size for f in (tmp / "out").rglob("*") if f.is_file()) / 2**20, 1)}
    return out


def bench_losses(scene_dir: str, init_dir: str, repeats: int) -> dict:
    from pipeline.data.dtu import load_scene
    from pipeline.init.io import depth_path, read_depth
    from pipeline.losses import gcf_loss, normal_consistency_losses
    from pipeline.priors.features import default_features

    scene = load_scene(scene_dir, view_ids=None)
    feats = [torch.from_numpy(default_features(im)) for im in scene.images]
    d = read_depth(depth_path(init_dir, scene.view_ids[0]))
    depth = torch.from_numpy(d.depth_mm).requires_grad_()
    mask = torch.from_numpy(d.valid)
    src = [(scene.K[i], scene.world_to_cam[i], feats[i]) for i in (1, 2)]
    times = []
    for _ in range(repeats + 1):  # the first run warms up
        t = time.perf_counter()
        gcf_loss(depth, scene.K[0], scene.world_to_cam[0], feats[0], src, valid=mask).backward()
        times.append(time.perf_counter() - t)
    n = torch.nn.functional.normalize(torch.randn(3, scene.height, scene.width), dim=0).requires_grad_()
    m = torch.nn.functional.normalize(torch.randn(3, scene.height, scene.width), dim=0)
    ntimes = []
    for _ in range(repeats + 1):
        t = time.perf_counter()
        sum(normal_consistency_losses(n, m, mask)).backward()
        ntimes.append(time.perf_counter() - t)
    return {"size": f"{scene.width}x{scene.height}", "views": scene.view_ids,
            "gcf_loss_fwd_bwd_s_median": round(statistics.median(times[1:]), 3),
            "gcf_points": int(mask.sum()), "gcf_channels": int(feats[0].shape[0]), "gcf_sources": 2,
            "normal_losses_fwd_bwd_s_median": round(statistics.median(ntimes[1:]), 4),
            "torch_threads": torch.get_num_threads()}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="data/scenes/scan24", help="prepared scene")
    p.add_argument("--init-dir", default="data/init/scan24", help="its init output (depth maps)")
    p.add_argument("--repeats", type=int, default=3, help="runs per configuration")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")
    p.add_argument("--out", default="reports/priors/stage_benchmark.json", help="JSON to write")


def run(args: argparse.Namespace) -> int:
    if args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    atomic.check_output_file(args.out)  # refused now, not after the runs
    for path in (Path(args.scene), Path(args.init_dir)):
        if not path.is_dir():
            raise FileNotFoundError(f"{path}: not found (run `dvc repro init@scan24`, or pass --scene/--init-dir)")
    params = load_params(args.params)
    with tempfile.TemporaryDirectory(prefix="bench_priors_") as tmp:
        stage = bench_stage(args.scene, args.init_dir, params, args.repeats, Path(tmp))
    losses = bench_losses(args.scene, args.init_dir, args.repeats)
    facts = provenance()
    result = {"scene": args.scene, "init": args.init_dir, "size": losses.pop("size"), "views": losses.pop("views"),
              "repeats": args.repeats, "cpu": facts["cpu"], "cpu_count": facts["cpu_cores"],
              "commit": facts["commit"], "load_average_1min": facts["load_average_1min"],
              "stage": stage, "losses_float32_cpu": losses}
    atomic.write_text(args.out, json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0
