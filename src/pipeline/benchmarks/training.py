"""``gcgs bench-train``: where a training iteration's time goes.

Builds the trainer of one prepared scene (its init output and, when the loss reads them, its
priors) with params' ``optimize`` / ``loss`` sections or a variant's (``--variant``, e.g.
``sa_paper``), runs a few warm-up iterations, jumps to iteration ``--at`` (so the terms that
start late are on: L_mv, L_d, L_dn), steps until every view has been trained there (what the
late terms cache per view is built once per run, not in the timed steps) and times
``--iterations`` iterations under cProfile.
The time is split by what runs:

* the rasterizer's numba kernels: the forward compositing, the backward compositing and its
  per-surfel reduction, the per-surfel set-up and tile binning;
* the torch autograd engine outside them (the backward of every loss term);
* the forward of the loss terms (photometric, multi-view, depth-normal, ...);
* the rest: the optimizer step, densification, the rasterizer's Python wrapper, the loop.

Shares are what compares between machines and loads; the seconds are this machine's at
the recorded load. Writes ``--out`` (JSON) and the Markdown beside it.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import time
from pathlib import Path

import torch

from pipeline import atomic
from pipeline.benchmarks.rasterizer import kernel_seconds
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.measure import provenance

# category -> the rasterizer's kernels in it (cProfile's own time): the numba kernels of the
# cpu backend and the simd backend's C++ runners (``simd.NAME``, see bench-raster's KERNEL_PARTS).
KERNELS = {
    "raster forward kernel": ("forward", "simd.forward_all"),
    "raster backward kernels": ("backward", "simd.backward_all", "reduce_and_chain"),
    "raster set-up and binning": (
        "preprocess", "break_depth_ties", "bin_tiles", "schedule_tiles",
        "simd.preprocess_all", "simd.depth_order", "simd.bin_tiles",
    ),
}
LOSS_KERNELS = "loss kernels (L_mv's patches, warp and NCC; SSIM's blur; L_smooth; L_dn)"
AUTOGRAD = "torch autograd (loss terms' backward)"
LOSS_FORWARD = "loss terms' forward (torch)"
REST = "rest (optimizer, densification, wrappers, loop)"
CATEGORIES = list(KERNELS) + [LOSS_KERNELS, AUTOGRAD, LOSS_FORWARD, REST]
# The loss terms' numba kernels: (module file, function) -> whether the forward calls it
# (its time then lies inside the loss terms' cumulative time); the blur serves both passes.
_LOSS_KERNEL_FUNCS = {
    ("losses/_mv_kernels.py", "warp_ncc_forward"): True,
    ("losses/_mv_kernels.py", "patch_moments"): True,
    ("losses/_mv_kernels.py", "textured_grid"): True,
    ("losses/_mv_kernels.py", "warp_ncc_backward"): False,
    ("losses/_blur_kernels.py", "gaussian_blur"): None,
    ("losses/_smooth_kernels.py", "forward"): True,
    ("losses/_smooth_kernels.py", "backward"): False,
    ("losses/_dn_kernels.py", "forward"): True,
    ("losses/_dn_kernels.py", "backward"): False,
}


def _forward_share_of_blur(stats: pstats.Stats) -> float:
    """The share of ``photometric._blur``'s time spent under SSIM's forward (its caller
    ``_ssim_parts``; the rest is SSIM's and the blur's backward)."""
    for (path, _line, name), (_cc, _nc, _own, cum, callers) in stats.stats.items():
        if path.replace(os.sep, "/").endswith("losses/photometric.py") and name == "_blur" and cum > 0:
            fwd = sum(c[3] for (cpath, _l, cname), c in callers.items() if cname == "_ssim_parts")
            return min(fwd / cum, 1.0)
    return 0.0


def split_profile(stats: pstats.Stats, total_s: float) -> dict[str, float]:
    """Seconds per category of a cProfile run of training steps lasting ``total_s``: the
    kernels' and the autograd engine's own time, the loss terms' cumulative time (their
    torch calls included, the loss kernels they call not), and the rest."""
    out = dict.fromkeys(CATEGORIES, 0.0)
    own = kernel_seconds(stats)
    for category, funcs in KERNELS.items():
        out[category] = sum(own[f] for f in funcs)
    in_forward = 0.0
    blur_forward = _forward_share_of_blur(stats)
    for (path, _line, name), (_cc, _nc, own_s, cum, _callers) in stats.stats.items():
        path = path.replace(os.sep, "/")
        if name == "<method 'run_backward' of 'torch._C._EngineBase' objects>":
            out[AUTOGRAD] += own_s
        if path.endswith("optimize/train.py") and name == "loss_terms":
            out[LOSS_FORWARD] += cum
        for (suffix, func), forward in _LOSS_KERNEL_FUNCS.items():
            if path.endswith(suffix) and name == func:
                out[LOSS_KERNELS] += own_s
                in_forward += own_s * (blur_forward if forward is None else float(forward))
    out[LOSS_FORWARD] = max(out[LOSS_FORWARD] - in_forward, 0.0)
    out[REST] = max(total_s - sum(v for k, v in out.items() if k != REST), 0.0)
    return out


def bench_training(scene_dir: str | Path, init_dir: str | Path, priors_dir: str | Path | None,
                   cfg: OptimizeConfig, loss: LossConfig, at: int, iterations: int, warmup: int = 3) -> dict:
    """Time ``iterations`` training steps of a scene from iteration ``at`` (after ``warmup``
    steps from the start, which compile and warm the kernels, and enough steps at ``at`` to
    visit every view): seconds per iteration, the split (:func:`split_profile`) and what was
    trained."""
    from pipeline.optimize.train import Trainer
    from pipeline.rasterizer import resolve_backend
    from pipeline.runs.optimize import load_training_inputs

    if iterations < 1 or at < 0:
        raise ValueError(f"bench-train: need --iterations >= 1 and --at >= 0, got {iterations}, {at}")
    _, params, views = load_training_inputs(scene_dir, init_dir, priors_dir, cfg, loss)
    trainer = Trainer(params, views, cfg, loss, resolve_backend(cfg.backend))
    for _ in range(warmup):
        trainer.step()
    trainer.it = max(at, trainer.it)
    # The steps after the jump build what the late terms keep per view (L_mv's textured-pixel
    # masks, once per view and size): the rest of the view epoch and a whole one, so every
    # view's are built before the timed steps.
    for _ in range(len(trainer.queue) + views.num_views):
        trainer.step()
    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.enable()
    for _ in range(iterations):
        trainer.step()
    profiler.disable()
    total = time.perf_counter() - start
    split = split_profile(pstats.Stats(profiler), total)
    return {"s_per_iteration": round(total / iterations, 4), "iterations": iterations, "from_iteration": at,
            "surfels": int(trainer.params.num), "torch_threads": torch.get_num_threads(),
            "split_s_per_iteration": {k: round(v / iterations, 4) for k, v in split.items()},
            "split_share": {k: round(v / total, 3) for k, v in split.items()}}


def markdown(result: dict) -> str:
    lines = [f"# Where a training iteration goes: {result['scene']} ({result['config']})", "",
             f"Commit {result['commit']}, {result['cpu']} ({result['cpu_count']} cores), torch threads "
             f"{result['torch_threads']}, 1-minute load {result['load_average_1min']} before. "
             f"{result['iterations']} iterations from iteration {result['from_iteration']}, "
             f"{result['surfels']} surfels: {result['s_per_iteration']} s per iteration. "
             "Shares compare between machines and loads; seconds are this run's.", "",
             "| part | s per iteration | share |", "| --- | --- | --- |"]
    for k, s in result["split_s_per_iteration"].items():
        lines.append(f"| {k} | {s:.4f} | {result['split_share'][k]:.1%} |")
    return "\n".join(lines) + "\n"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default="data/scenes/synth_relief", help="prepared scene")
    p.add_argument("--init-dir", default="data/init/synth_relief", help="its init output (cloud, depth maps)")
    p.add_argument("--priors-dir", default=None, help="its priors output (needed when L_nor or L_gcf is on)")
    p.add_argument("--variant", default=None, help="train with this ablation variant's settings (e.g. sa_paper)")
    p.add_argument("--at", type=int, default=None,
                   help="iteration to time from (default: 85%% of the run, every term on)")
    p.add_argument("--iterations", type=int, default=20, help="iterations timed")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")
    p.add_argument("--out", default="reports/benchmarks/training.json", help="JSON to write (and .md beside it)")


def run(args: argparse.Namespace) -> int:
    from pipeline.config.variants import variant_training

    for out in (Path(args.out), Path(args.out).with_suffix(".md")):  # refused now, not after the training
        atomic.check_output_file(out)
    for path in (Path(args.scene), Path(args.init_dir)):
        if not path.is_dir():
            raise FileNotFoundError(f"{path}: not found (run `dvc repro`, or pass --scene/--init-dir)")
    params = load_params(args.params)
    if args.variant:
        _, cfg, loss = variant_training(params, args.variant)
    else:
        cfg, loss = section(OptimizeConfig, "optimize", params), section(LossConfig, "loss", params)
    at = int(0.85 * cfg.iterations) if args.at is None else args.at
    facts = provenance()
    result = {"scene": args.scene, "config": args.variant or "params' optimize and loss", "commit": facts["commit"],
              "cpu": facts["cpu"], "cpu_count": facts["cpu_cores"], "load_average_1min": facts["load_average_1min"],
              **bench_training(args.scene, args.init_dir, args.priors_dir, cfg, loss, at, args.iterations)}
    atomic.write_text(args.out, json.dumps(result, indent=2) + "\n")
    atomic.write_text(Path(args.out).with_suffix(".md"), markdown(result))
    print(markdown(result))
    return 0
