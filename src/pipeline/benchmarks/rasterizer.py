"""``gcgs bench-raster``: speed and memory of the cpu and reference backends and of the simd kernels.

Scenes: surfels tiling an object's surface seen from DTU camera 23 (``scenes.py``);
render colour + alpha + expected/median depth + normals + distortion, then back-
propagate random cotangents on all of them (``torch.autograd.backward`` with the cotangents
as the maps' gradients: no loss of the benchmark's own is timed). Writes ``rasterizer.json`` (one record per
backend and case) and ``rasterizer.md`` (a table with the cpu/reference speed ratio).

Each cpu case also splits its time by kernel (cProfile's own time of each numba kernel over
the timed runs, per run): the per-surfel set-up and binning, the forward compositing, the
backward compositing, the per-surfel reduction, and the rest (the Python wrapper and torch's
allocations).

The simd kernels (the ``simd`` backend, ``pipeline.rasterizer.simd``: the cpu backend with its compositing kernels in
C++, float32) are timed alternated with the cpu backend in the same case, so their ratio is
taken in one stretch of time on a machine whose speed drifts; skipped, with the reason, where
they cannot be built.

``pairs`` is the number of pixel-surfel pairs inside the support boxes (the work the
scene defines, identical for both backends); ``pairs_per_s = pairs / (forward_s +
backward_s)``. ``peak_mb`` is the peak resident memory above the level before the case
(:func:`pipeline.measure.measure`: the kernel's peak RSS, reset after returning freed heap
pages to the OS), i.e. the extra memory of one forward + backward, starting with no pooled
scratch buffers (``cpu.SCRATCH``); the timed runs that follow reuse the pool, as a training
loop does.
"""
from __future__ import annotations

import argparse
import cProfile
import json
import os
import platform
import pstats
import statistics
import time
from pathlib import Path

import numba
import torch

from pipeline import atomic
from pipeline.measure import measure
from pipeline.rasterizer import Surfels, rasterize
from pipeline.rasterizer import _kernels as K
from pipeline.rasterizer import cpu as cpu_backend
from pipeline.rasterizer import simd
from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels

SIZES = [(200, 150), (400, 300), (800, 600)]
COUNTS = [10_000, 50_000, 200_000]
QUICK = [(400, 300, 50_000)]
TARGET_CASE = (400, 300, 50_000)
TARGET_SECONDS = 0.15
TARGET_RATIO = 20.0
ISSUE20_CASE = (800, 600, 200_000)  # the paper's resolution with a full-size surfel cloud
ISSUE20_SECONDS = 0.15
ISSUE59_SECONDS = 0.10  # the same case through rasterize(..., "auto")
MAPS = ("features", "alpha", "depth_expected", "depth_median", "normal_cam", "normal_world", "distortion")
# Reference memory per evaluated (pixel, surfel) pair in a block, measured on small
# cases (float32 autograd graph of reference._composite); used to skip cases that
# would not fit.
REF_BYTES_PER_PAIR = 150
REF_BLOCK = 8
KERNEL_PARTS = {  # part of a render -> the kernels it runs (numba's in _kernels.py; rasterizer/simd.py's C++ runners)
    "set-up and binning": (
        "preprocess", "break_depth_ties", "bin_tiles", "schedule_tiles",
        "simd.preprocess_all", "simd.depth_order", "simd.bin_tiles",
    ),
    "forward compositing": ("gather_entries", "forward", "simd.forward_all"),
    "backward compositing": ("backward", "simd.backward_all"),
    "per-surfel reduction": ("reduce_and_chain",),
}


def kernel_seconds(stats: pstats.Stats) -> dict[str, float]:
    """cProfile's own seconds of each kernel (numba kernels of ``rasterizer/_kernels.py``, the C++ runners of ``rasterizer/simd.py``)."""
    out = {f: 0.0 for funcs in KERNEL_PARTS.values() for f in funcs}
    for (path, _line, name), (_cc, _nc, own, _cum, _callers) in stats.stats.items():
        path = path.replace(os.sep, "/")
        key = name if path.endswith("rasterizer/_kernels.py") else f"simd.{name}" if path.endswith("rasterizer/simd.py") else None
        if key in out:
            out[key] += own
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--quick", action="store_true", help="only the 400x300 / 50k case, every backend")
    parser.add_argument("--out-dir", type=Path, default=Path("reports/benchmarks"), help="where to write the reports")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per cpu case (median reported)")
    parser.add_argument(
        "--reference-budget-gb", type=float, default=8.0, help="skip reference cases estimated above this memory"
    )


def _leaves(s: Surfels) -> Surfels:
    return Surfels(*(t.detach().clone().requires_grad_(True) for t in (s.means, s.quats, s.scales, s.opacities, s.features)))


def _time_once(s: Surfels, cam, backend: str, cot: dict) -> tuple[float, float]:
    s = _leaves(s)
    kw = {"reference_block": REF_BLOCK} if backend == "reference" else {}
    t0 = time.perf_counter()
    out = rasterize(s, cam, backend, **kw)
    t1 = time.perf_counter()
    torch.autograd.backward([getattr(out, k) for k in MAPS], [cot[k] for k in MAPS])
    t2 = time.perf_counter()
    return t1 - t0, t2 - t1


def _reference_pairs(s: Surfels, cam) -> int:
    """(pixel, surfel) pairs the block-culled reference evaluates."""
    with torch.no_grad():
        g = cpu_backend.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    box = torch.from_numpy(g.box[g.radii > 0])
    total = 0
    for y0 in range(0, cam.height, REF_BLOCK):
        for x0 in range(0, cam.width, REF_BLOCK):
            y1, x1 = min(y0 + REF_BLOCK, cam.height), min(x0 + REF_BLOCK, cam.width)
            hit = (box[:, 0] < x1) & (box[:, 1] >= x0) & (box[:, 2] < y1) & (box[:, 3] >= y0)
            total += int(hit.sum()) * (x1 - x0) * (y1 - y0)
    return total


def _centre_depth_deviation(s: Surfels, cam) -> dict:
    """How far gsplat's centre-depth compositing (the cuda backend) is from the
    intersection depth, measured with the cpu kernel on the same weights: render the
    centre depth as a feature channel and compare with ``depth_expected``."""
    with torch.no_grad():
        z_c = s.means.double() @ cam.world_to_cam[2, :3] + cam.world_to_cam[2, 3]
        probe = Surfels(s.means, s.quats, s.scales, s.opacities, z_c[:, None].to(s.means.dtype))
        out = rasterize(probe, cam, "cpu")
        hit = out.alpha > 0.5
        centre = out.features[..., 0] / (out.alpha + 1e-6)
        dev = (centre - out.depth_expected)[hit].abs().double()
    if dev.numel() == 0:
        return {}
    return {
        "centre_depth_dev_mean": float(dev.mean()),
        "centre_depth_dev_p99": float(torch.quantile(dev, 0.99)),
        "depth_mean": float(out.depth_expected[hit].double().mean()),
    }


def _bench_case(W: int, H: int, N: int, backend: str, repeats: int, budget_gb: float) -> dict:
    cam, norm_to_world = dtu_camera(W, H)
    s = object_surfels(N, norm_to_world, seed=0)
    with torch.no_grad():
        g = cpu_backend.prepare(s.means, s.quats, s.scales, s.opacities, cam)
    rec = {
        "backend": backend, "width": W, "height": H, "num_surfels": N, "pairs": g.box_pixels,
        "tile_pairs": g.num_pairs, "visible_surfels": int((g.radii > 0).sum()),
    }  # fmt: skip
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        shapes = {k: getattr(rasterize(s, cam, "cpu"), k).shape for k in MAPS}
    cot = {k: torch.randn(shapes[k], generator=gen) for k in MAPS}
    if backend == "simd":
        ok, why = simd.available()
        if not ok:
            rec["skipped"] = f"simd kernels unavailable: {why.splitlines()[0]}"
            return rec
    if backend == "reference":
        ref_pairs = _reference_pairs(s, cam)
        est_gb = ref_pairs * REF_BYTES_PER_PAIR / 2**30
        rec.update(reference_pairs=ref_pairs, estimated_gb=round(est_gb, 2))
        if est_gb > budget_gb:
            rec["skipped"] = f"estimated {est_gb:.1f} GB > budget {budget_gb:g} GB"
            return rec
        repeats = 1
    load_before = os.getloadavg()[0]
    fwd, bwd = [], []
    cpu_backend.SCRATCH.clear()  # the peak includes the cpu backend's scratch buffers
    with measure() as mem:
        f, b = _time_once(s, cam, backend, cot)
    peak = mem.added_mb if mem.peak_is_own else None  # None: this kernel cannot reset the peak
    if backend in ("cpu", "simd"):  # the peak run doubles as warm-up; time fresh runs
        profiler = cProfile.Profile()
        alternated = []
        for _ in range(repeats):
            if backend == "simd":  # the cpu backend between the runs: a ratio in one stretch of time
                alternated.append(sum(_time_once(s, cam, "cpu", cot)))
            profiler.enable()
            # the simd kernels through the public API: ``auto`` resolves to them where they build
            f, b = _time_once(s, cam, "auto" if backend == "simd" else backend, cot)
            profiler.disable()
            fwd.append(f)
            bwd.append(b)
        if alternated:
            rec["cpu_alternated_total_s"] = round(statistics.median(alternated), 4)
        own = kernel_seconds(pstats.Stats(profiler))
        split = {part: sum(own[f] for f in funcs) / repeats for part, funcs in KERNEL_PARTS.items()}
        split["rest"] = max((sum(fwd) + sum(bwd)) / repeats - sum(split.values()), 0.0)
        rec["split_s"] = {k: round(v, 6) for k, v in split.items()}
    else:
        fwd, bwd = [f], [b]
    f_med, b_med = statistics.median(fwd), statistics.median(bwd)
    rec.update(
        forward_s=round(f_med, 4),
        backward_s=round(b_med, 4),
        total_s=round(f_med + b_med, 4),
        best_total_s=round(min(x + y for x, y in zip(fwd, bwd)), 4),
        repeats=len(fwd),
        pairs_per_s=round(g.box_pixels / (f_med + b_med)),
        peak_mb=None if peak is None else round(peak, 1),
        kept_mb=None if backend != "cpu" else round(
            (int(g.rec_tile_start[-1]) * K.R_SIZE * s.means.element_size() + g.num_pairs * (K.S_FIXED + 3) * 8
             + g.num_pairs * (K.E_FEAT + 3) * 8 + g.tile_list.nbytes + g.slot_of_entry.nbytes) / 2**20, 1),  # fmt: skip
        load_avg_1min=[round(load_before, 2), round(os.getloadavg()[0], 2)],
    )
    if backend == "cpu":
        rec.update(_centre_depth_deviation(s, cam))
    return rec


def _markdown(records: list[dict], meta: dict) -> str:
    lines = [
        "# Rasterizer benchmark",
        "",
        f"Machine: {meta['machine']}; numba threads {meta['numba_threads']}, torch threads {meta['torch_threads']}, "
        f"numba threading layer `{meta['threading_layer']}`. The machine is shared: 1-minute load average "
        "before/after each case is in the JSON (`load_avg_1min`); with load above the core count, times are inflated.",
        "",
        f"cpu kernels: first use in this process took {meta['compile_s']:.1f} s "
        f"({'loaded from numba cache' if meta['from_cache'] else 'compiled: cold cache'}).",
        "",
        "Forward = render colour, alpha, expected/median depth, camera/world normals and distortion; backward = "
        "gradients of all of them (random cotangents) w.r.t. means, quats, scales, opacities, colours. "
        "Times are medians (cpu: of several runs; reference: one run, block-culled pure PyTorch, blocks of "
        f"{REF_BLOCK} px).",
        "",
        "| image | surfels | pairs | cpu fwd s | cpu bwd s | cpu total s | cpu peak MB | ref fwd s | ref bwd s | ref total s | ref peak MB | cpu / ref speed |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    by_case: dict[tuple, dict] = {}
    for r in records:
        by_case.setdefault((r["width"], r["height"], r["num_surfels"]), {})[r["backend"]] = r
    for (W, H, N), recs in by_case.items():
        c, r = recs.get("cpu", {}), recs.get("reference", {})
        ratio = f"{r['total_s'] / c['total_s']:.1f}x" if "total_s" in r and "total_s" in c else "-"
        ref = [f"{r[k]}" if k in r else ("skipped" if "skipped" in r else "-") for k in ("forward_s", "backward_s", "total_s", "peak_mb")]
        lines.append(
            f"| {W}x{H} | {N} | {c.get('pairs', r.get('pairs', '-'))} | {c.get('forward_s', '-')} | {c.get('backward_s', '-')} | "
            f"{c.get('total_s', '-')} | {c.get('peak_mb', '-')} | {' | '.join(ref)} | {ratio} |"
        )
    target = by_case.get(TARGET_CASE, {})
    c, r = target.get("cpu"), target.get("reference")
    lines += ["", "## Targets (400x300, 50k surfels)", ""]
    if c:
        ok = c["total_s"] <= TARGET_SECONDS
        lines.append(
            f"- forward + backward <= {TARGET_SECONDS} s: **{'met' if ok else 'missed'}** "
            f"(median {c['total_s']} s, best {c['best_total_s']} s, load {c['load_avg_1min']})"
        )
    if c and r and "total_s" in r:
        ratio = r["total_s"] / c["total_s"]
        lines.append(f"- >= {TARGET_RATIO:g}x the reference: **{'met' if ratio >= TARGET_RATIO else 'missed'}** ({ratio:.1f}x)")
    simd_recs = [r for r in records if r["backend"] == "simd"]
    if simd_recs:
        lines += [
            "",
            "## The simd kernels against the cpu backend",
            "",
            "The cpu backend with its two compositing kernels in C++ (the `simd` backend, float32 "
            "lanes; docs/rasterizer.md \"The simd kernels\"), timed through `rasterize(surfels, camera, \"auto\")` "
            "(which resolves to it here), each timed run preceded by a cpu run of the same "
            "case, so the ratio is taken in one stretch of time:",
            "",
            "| image | surfels | cpu total s (alternated) | simd fwd s | simd bwd s | simd total s | simd / cpu |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in simd_recs:
            if "skipped" in r:
                lines.append(f"| {r['width']}x{r['height']} | {r['num_surfels']} | skipped: {r['skipped']} | | | | |")
                continue
            ratio = r["total_s"] / r["cpu_alternated_total_s"]
            lines.append(
                f"| {r['width']}x{r['height']} | {r['num_surfels']} | {r['cpu_alternated_total_s']} | {r['forward_s']} | "
                f"{r['backward_s']} | {r['total_s']} | {ratio:.2f} |"
            )
        case = by_case.get(ISSUE20_CASE, {})
        best = [(n, case[n]["total_s"]) for n in ("cpu", "simd") if "total_s" in case.get(n, {})]
        if best:
            W, H, N = ISSUE20_CASE
            name, secs = min(best, key=lambda x: x[1])
            lines += ["", f"Issue 20's target, {W}x{H} / {N} surfels forward + backward <= {ISSUE20_SECONDS} s: "
                      f"**{'met' if secs <= ISSUE20_SECONDS else 'missed'}** (best: {name}, {secs} s)."]  # fmt: skip
        auto = case.get("simd", {})
        if "total_s" in auto:
            lines += ["", f"Issue 59's target, the same case through `auto` <= {ISSUE59_SECONDS} s: "
                      f"**{'met' if auto['total_s'] <= ISSUE59_SECONDS else 'missed'}** ({auto['total_s']} s, best "
                      f"{auto['best_total_s']} s; {auto['total_s'] / auto['cpu_alternated_total_s']:.2f}x the numba "
                      "kernels alternated)."]  # fmt: skip
    skipped = [r for r in records if "skipped" in r and r["backend"] == "reference"]
    if skipped:
        lines += ["", "Reference cases skipped (would not fit in memory): " + ", ".join(
            f"{r['width']}x{r['height']}/{r['num_surfels']} ({r['skipped']})" for r in skipped)]  # fmt: skip
    split = [r for r in records if "split_s" in r]
    if split:
        parts = list(split[0]["split_s"])
        lines += [
            "",
            "## Where the cpu backend's (and the simd kernels') time goes",
            "",
            "Seconds per forward + backward (cProfile's own time of each kernel over the timed runs; rest = the "
            "Python wrapper and allocations), and each part's share of the total:",
            "",
            "| image | surfels | kernels | " + " | ".join(parts) + " |",
            "|---|---|---|" + "---|" * len(parts),
        ]
        for r in split:
            total = sum(r["split_s"].values()) or 1.0
            cells = [f"{r['split_s'][k]:.4f} ({r['split_s'][k] / total:.0%})" for k in parts]
            lines.append(f"| {r['width']}x{r['height']} | {r['num_surfels']} | {r['backend']} | " + " | ".join(cells) + " |")
    dev = [r for r in records if "centre_depth_dev_mean" in r]
    if dev:
        lines += [
            "",
            "## cuda backend: centre depth instead of intersection depth",
            "",
            "gsplat composites each surfel's centre depth. Measured with the cpu kernel on the same weights "
            "(pixels with alpha > 0.5, world units = mm):",
            "",
            "| image | surfels | mean depth | mean abs deviation | 99th percentile |",
            "|---|---|---|---|---|",
        ]
        for r in dev:
            lines.append(
                f"| {r['width']}x{r['height']} | {r['num_surfels']} | {r['depth_mean']:.1f} | "
                f"{r['centre_depth_dev_mean']:.4f} | {r['centre_depth_dev_p99']:.4f} |"
            )
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    if args.repeats < 1:
        raise ValueError(f"--repeats must be >= 1, got {args.repeats}")
    cases = QUICK if args.quick else [(W, H, N) for (W, H) in SIZES for N in COUNTS]
    # --quick writes beside the full run's report instead of replacing it.
    stem = "rasterizer_quick" if args.quick else "rasterizer"
    json_path, md_path = args.out_dir / f"{stem}.json", args.out_dir / f"{stem}.md"
    for path in (json_path, md_path):  # refused now, not after minutes of timing
        atomic.check_output_file(path)
    compile_s = cpu_backend.warm_up()
    # numba counts, per kernel, the signatures it had to compile rather than load.
    kernels = (K.preprocess, K.break_depth_ties, K.bin_tiles, K.schedule_tiles, K.gather_entries, K.forward,
               K.backward, K.reduce_and_chain)
    misses = sum(sum(d.stats.cache_misses.values()) for d in kernels)
    meta = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "numba_threads": numba.get_num_threads(),
        "torch_threads": torch.get_num_threads(),
        "threading_layer": numba.threading_layer(),
        "compile_s": compile_s,
        "from_cache": misses == 0,
    }
    print(f"cpu kernels ready in {compile_s:.1f} s ({'cache' if meta['from_cache'] else 'compiled'})", flush=True)
    records = []
    jobs = [(c, b) for c in cases for b in ("cpu", "simd", "reference")]
    for i, ((W, H, N), backend) in enumerate(jobs, 1):
        rec = _bench_case(W, H, N, backend, args.repeats, args.reference_budget_gb)
        rec["compile_s"] = round(compile_s, 2)
        records.append(rec)
        if "skipped" in rec:
            print(f"[{i}/{len(jobs)}] {backend:9s} {W}x{H} {N:>6d} surfels: skipped ({rec['skipped']})", flush=True)
        else:
            print(
                f"[{i}/{len(jobs)}] {backend:9s} {W}x{H} {N:>6d} surfels: forward {rec['forward_s']:.3f} s, "
                f"backward {rec['backward_s']:.3f} s, {rec['pairs_per_s']:.3g} pairs/s, "
                f"peak {rec['peak_mb']} MB, load {rec['load_avg_1min'][0]:.1f}",
                flush=True,
            )
    atomic.write_text(json_path, json.dumps(records, indent=1) + "\n")
    atomic.write_text(md_path, _markdown(records, meta))
    print(f"wrote {json_path} and {md_path}")
    return 0
