"""Time and peak memory of the priors stage and of the prior losses on the bundled scan.

Run from the repository root after `dvc repro init@scan24` (needs data/scenes/scan24 and
data/init/scan24):  python reports/priors/bench.py  -> reports/priors/stage_benchmark.json
Each stage configuration runs REPEATS times in a fresh process under /usr/bin/time -v
(wall time and max RSS of the whole process: Python, torch, onnxruntime imports included).
"""
from __future__ import annotations

import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

REPEATS = 3
SCENE, INIT = "data/scenes/scan24", "data/init/scan24"
OUT = Path(__file__).resolve().parent / "stage_benchmark.json"


def timed_run(args: list[str]) -> tuple[float, float]:
    res = subprocess.run(["/usr/bin/time", "-v", *args], capture_output=True, text=True, check=True)
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): (\S+)", res.stderr).group(1)
    secs = sum(float(x) * 60**i for i, x in enumerate(reversed(wall.split(":"))))
    rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", res.stderr).group(1))
    return secs, rss_kb / 1024.0


def bench_stage(tmp: Path) -> dict:
    params = yaml.safe_load(Path("params.yaml").read_text())
    configs = {"normals+features (default)": {}, "normals only (lambda_gcf=0)": {"lambda_gcf": 0.0},
               "features only (lambda_nor=0)": {"lambda_nor": 0.0}}
    out = {}
    for name, loss in configs.items():
        p = dict(params, loss={**params["loss"], **loss})
        pfile = tmp / f"params_{len(out)}.yaml"
        pfile.write_text(yaml.safe_dump(p))
        runs = [timed_run(["gcgs", "priors", "--scene", SCENE, "--init-dir", INIT, "--out-dir",
                           str(tmp / "out"), "--params", str(pfile)]) for _ in range(REPEATS)]
        info = json.loads((tmp / "out" / "priors.json").read_text())
        out[name] = {"wall_s_median": round(statistics.median(r[0] for r in runs), 2),
                     "max_rss_mb_max": round(max(r[1] for r in runs), 1),
                     "in_stage_s": {k: info[k] for k in ("load_s", "normals_s", "features_s", "time_s")},
                     "output_mb": round(sum(f.stat().st_size for f in (tmp / "out").rglob("*") if f.is_file()) / 2**20, 1)}
    return out


def bench_losses() -> dict:
    from pipeline.data.dtu import load_scene
    from pipeline.init.io import depth_path, read_depth
    from pipeline.losses import gcf_loss, normal_consistency_losses
    from pipeline.priors.features import default_features

    scene = load_scene(SCENE, view_ids=None)
    feats = [torch.from_numpy(default_features(im)) for im in scene.images]
    d = read_depth(depth_path(INIT, scene.view_ids[0]))
    depth = torch.from_numpy(d.depth_mm).requires_grad_()
    mask = torch.from_numpy(d.valid)
    src = [(scene.K[i], scene.world_to_cam[i], feats[i]) for i in (1, 2)]
    times = []
    for _ in range(REPEATS + 1):
        t = time.perf_counter()
        gcf_loss(depth, scene.K[0], scene.world_to_cam[0], feats[0], src, mask=mask).backward()
        times.append(time.perf_counter() - t)
    n = torch.nn.functional.normalize(torch.randn(3, scene.height, scene.width), dim=0).requires_grad_()
    m = torch.nn.functional.normalize(torch.randn(3, scene.height, scene.width), dim=0)
    ntimes = []
    for _ in range(REPEATS + 1):
        t = time.perf_counter()
        sum(normal_consistency_losses(n, m, mask)).backward()
        ntimes.append(time.perf_counter() - t)
    return {"gcf_loss_fwd_bwd_s_median": round(statistics.median(times[1:]), 3),
            "gcf_points": int(mask.sum()), "gcf_channels": int(feats[0].shape[0]), "gcf_sources": 2,
            "normal_losses_fwd_bwd_s_median": round(statistics.median(ntimes[1:]), 4),
            "torch_threads": torch.get_num_threads()}


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        stage = bench_stage(Path(tmp))
    result = {"scene": SCENE, "init": INIT, "size": "800x600", "views": [23, 24, 33], "repeats": REPEATS,
              "cpu": platform.processor() or platform.machine(), "cpu_count": os.cpu_count(),
              "stage": stage, "losses_float32_cpu": bench_losses()}
    OUT.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path.cwd() / "src"))
    raise SystemExit(main())
