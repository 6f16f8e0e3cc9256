"""`rasterize(surfels, camera, "auto")` against the numba kernels (`"cpu"`) through the public
API, forward + backward, at the bench-raster scene's 800x600 / 200k surfels, alternated in one
run (medians of --repeats each, after one warm-up each).

    python experiments/simd_default_2026-12-05/auto_vs_cpu.py [--repeats 7]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from pipeline.benchmarks.rasterizer import MAPS
from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels
from pipeline.rasterizer import Surfels, rasterize, resolve_backend


def once(s: Surfels, cam, backend: str, cot: dict) -> tuple[float, float]:
    s = Surfels(*(t.detach().clone().requires_grad_(True) for t in (s.means, s.quats, s.scales, s.opacities, s.features)))
    t0 = time.perf_counter()
    out = rasterize(s, cam, backend)
    t1 = time.perf_counter()
    sum((getattr(out, k) * cot[k]).sum() for k in MAPS).backward()
    return t1 - t0, time.perf_counter() - t1


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=800)
    ap.add_argument("--height", type=int, default=600)
    ap.add_argument("--surfels", type=int, default=200_000)
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    cam, norm_to_world = dtu_camera(args.width, args.height)
    s = object_surfels(args.surfels, norm_to_world, seed=0)
    with torch.no_grad():
        out = rasterize(s, cam, "cpu")
    gen = torch.Generator().manual_seed(0)
    cot = {k: torch.randn(getattr(out, k).shape, generator=gen) for k in MAPS}
    covered = float((out.alpha > 0.5).float().mean())
    times = {"auto": [], "cpu": []}
    for b in times:
        once(s, cam, b, cot)  # warm-up: compile / load kernels, fill the scratch pool
    for _ in range(args.repeats):
        for b in times:
            times[b].append(once(s, cam, b, cot))
    res = {"auto_resolves_to": resolve_backend("auto"), "image": [args.width, args.height], "surfels": args.surfels,
           "alpha_over_half_share": round(covered, 3), "threads": torch.get_num_threads()}
    for b, ts in times.items():
        res[b] = {"forward_s": statistics.median(t[0] for t in ts), "backward_s": statistics.median(t[1] for t in ts),
                  "total_s": statistics.median(t[0] + t[1] for t in ts)}
    res["auto_over_cpu"] = res["auto"]["total_s"] / res["cpu"]["total_s"]
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
