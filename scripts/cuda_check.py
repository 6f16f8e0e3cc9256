"""The GPU half of the cuda backend's check (docs/rasterizer.md, "The cuda backend, run").

On a machine with CUDA and gsplat, for each scene: train with ``optimize.backend=cuda``
(params.yaml's preset otherwise), then with ``cpu`` for the time ratio on the same machine,
and save the cuda backend's renders at the input views of the cuda-trained surfels and of
the committed cpu-trained ones (``data/surfels/SCENE/surfels.ply``) for
``scripts/cuda_compare.py``, which meshes, scores and compares them on the CPU machine.

    python scripts/cuda_check.py OUT [--scenes synth_thin scan24] [--no-cpu]

Writes ``OUT/SCENE_cuda_surfels.ply``, ``OUT/SCENE_renders.npz`` and ``OUT/times.json``.
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
import traceback
from pathlib import Path

import numpy as np
import torch

from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.data.dtu import load_scene
from pipeline.rasterizer import Camera, rasterize
from pipeline.runs.optimize import run_optimize
from pipeline.surfels import read_surfel_ply


def train_once(scene: str, backend: str, work: Path) -> tuple[Path, float]:
    params = load_params("params.yaml")
    cfg = section(OptimizeConfig, "optimize", params, {"backend": backend})
    loss = section(LossConfig, "loss", params)
    if loss.lambda_nor > 0 or loss.lambda_gcf > 0:
        raise SystemExit("this check runs without priors: loss.lambda_nor and loss.lambda_gcf must be 0")
    no_priors = work / "no_priors"
    no_priors.mkdir(exist_ok=True)
    out = work / f"{scene}_{backend}"
    t = time.perf_counter()
    run_optimize(f"data/scenes/{scene}", f"data/init/{scene}", no_priors, out, cfg, loss,
                 checkpoint=work / f"{scene}_{backend}.ckpt", live_dir=None, progress=False)
    return out / "surfels.ply", time.perf_counter() - t


def renders_at_inputs(scene_name: str, surfels_ply: Path) -> dict[str, np.ndarray]:
    """The cuda backend's maps at the scene's input views (normalised frame, as training
    renders them): depth in mm, float16 alpha and camera-frame normals."""
    scene = load_scene(f"data/scenes/{scene_name}", view_ids=None)
    params = read_surfel_ply(surfels_ply, scene.norm_to_world)
    surf = params.surfels(params.sh_degree_max)
    w2c = scene.world_to_cam_normalised()
    maps: dict[str, list] = {"depth_median_mm": [], "depth_expected_mm": [], "alpha": [], "normal_cam": []}
    with torch.no_grad():
        for i in range(scene.num_views):
            cam = Camera(scene.K[i], w2c[i], scene.width, scene.height)  # the mesh stage's camera
            out = rasterize(surf, cam, "cuda")
            maps["depth_median_mm"].append(out.depth_median.numpy() * scene.norm_scale_mm)
            maps["depth_expected_mm"].append(out.depth_expected.numpy() * scene.norm_scale_mm)
            maps["alpha"].append(out.alpha.numpy().astype(np.float16))
            maps["normal_cam"].append(out.normal_cam.numpy().astype(np.float16))
    return {k: np.stack(v) for k, v in maps.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--scenes", nargs="+", default=["synth_thin", "scan24"])
    ap.add_argument("--no-cpu", action="store_true", help="skip the cpu backend's training (time ratio)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    times: dict = {"device": torch.cuda.get_device_name(0), "torch": torch.__version__,
                   "cpu_threads": torch.get_num_threads()}
    work = Path(tempfile.mkdtemp(prefix="cuda_check_"))

    def save() -> None:
        (out / "times.json").write_text(json.dumps(times, indent=2) + "\n")

    for scene in args.scenes:  # the cuda runs first: the cpu ones only give the time ratio
        entry = times.setdefault(scene, {})
        try:
            ply, wall = train_once(scene, "cuda", work)
            entry["cuda_train_wall_s"] = round(wall, 1)
            shutil.copy(ply, out / f"{scene}_cuda_surfels.ply")
            save()
            maps = {f"cuda_trained/{k}": v for k, v in renders_at_inputs(scene, ply).items()}
            committed = Path(f"data/surfels/{scene}/surfels.ply")
            if committed.is_file():
                maps |= {f"cpu_trained/{k}": v for k, v in renders_at_inputs(scene, committed).items()}
            np.savez_compressed(out / f"{scene}_renders.npz", **maps)
        except Exception:
            entry["error"] = traceback.format_exc()
            print(entry["error"], flush=True)
        save()
        print(scene, entry, flush=True)
    for scene in [] if args.no_cpu else args.scenes:
        _, wall = train_once(scene, "cpu", work)
        times[scene]["cpu_train_wall_s"] = round(wall, 1)
        save()
        print(scene, times[scene], flush=True)

if __name__ == "__main__":
    main()
