"""L_mv through the fused kernels against its torch composition, and whole training
iterations with each, alternated in one process on one thread (CPU time, medians).

    GCGS_THREADS=1 python experiments/losses_fused_2026-12-05/alternate.py [SCENE] [--data DIR]

Builds the `fast` trainer of the scene from the DVC outputs under DIR (scenes/, init/,
priors/), steps to iteration 425 (L_mv, L_d and L_dn on, 400x300), captures one L_mv call
and times it 20 times with each kernel, then 20 training iterations with each.
"""
from __future__ import annotations

import argparse
import importlib
import time

import numpy as np

from pipeline.threads import configure_threads

configure_threads()

from pipeline.config.loss import LossConfig  # noqa: E402
from pipeline.config.optimize import OptimizeConfig  # noqa: E402
from pipeline.config.params import compose_params, section  # noqa: E402
from pipeline.losses import multiview as mv  # noqa: E402
from pipeline.rasterizer import resolve_backend  # noqa: E402
from pipeline.runs.optimize import load_training_inputs  # noqa: E402

train = importlib.import_module("pipeline.optimize.train")  # the package exports a function of that name


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", nargs="?", default="synth_relief")
    ap.add_argument("--data", default="data")
    args = ap.parse_args()
    p = compose_params(["optimize=fast"])
    cfg, loss = section(OptimizeConfig, "optimize", p), section(LossConfig, "loss", p)
    d, s = args.data, args.scene
    _, params, views = load_training_inputs(f"{d}/scenes/{s}", f"{d}/init/{s}", f"{d}/priors/{s}", cfg, loss)
    tr = train.Trainer(params, views, cfg, loss, resolve_backend(cfg.backend))
    for _ in range(3):
        tr.step()
    tr.it = 425
    for _ in range(len(tr.queue) + views.num_views):
        tr.step()
    original, captured, kernel = mv.multiview_consistency, {}, {"name": "auto"}

    def capture(*a, **kw):
        captured.update(a=a, kw=kw)
        return original(*a, **kw)

    train.multiview_consistency = capture
    tr.step()
    a, kw = captured["a"], captured["kw"]

    def one(name):
        dep, nor = a[0].detach().clone().requires_grad_(), a[1].detach().clone().requires_grad_()
        t0 = time.process_time()
        out = original(dep, nor, *a[2:], **kw, kernel=name)
        t1 = time.process_time()
        (out["photo"] + out["geo"]).backward()
        return t1 - t0, time.process_time() - t1

    times = {"fused": [], "torch": []}
    for _ in range(20):
        for name in times:
            times[name].append(one(name))
    print(f"{s}: L_mv of {len(a[2])} points, {len(a[6])} sources, ms (forward / backward):")
    for name, v in times.items():
        f, b = 1e3 * np.median(np.array(v), 0)
        print(f"  {name}: {f:.1f} / {b:.1f}")
    train.multiview_consistency = lambda *x, **k: original(*x, **k, kernel=kernel["name"])
    its = {"fused": [], "torch": []}
    for _ in range(4):
        for name in its:
            kernel["name"] = name
            t0 = time.process_time()
            for _ in range(5):
                tr.step()
            its[name].append((time.process_time() - t0) / 5)
    print("  iteration CPU s: " + ", ".join(f"{n} {np.median(v):.4f}" for n, v in its.items()))


if __name__ == "__main__":
    main()
