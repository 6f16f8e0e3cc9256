"""Per loss term of a `fast` training at iteration 425 (400x300): its forward time and the time of its backward to the rendered maps (each term alone, `torch.autograd.grad`), and the rasterizer's backward from all maps; medians over 30 iterations. Run from the checkout: python term_times.py [SCENE]"""
import time, sys, statistics
import torch
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
import importlib; T = importlib.import_module("pipeline.optimize.train")
from pipeline.rasterizer import resolve_backend, rasterize
from pipeline.runs.optimize import load_training_inputs
scene = sys.argv[1] if len(sys.argv) > 1 else "synth_relief"
params = load_params("params.yaml")
cfg, loss = section(OptimizeConfig, "optimize", params), section(LossConfig, "loss", params)
_, p, views = load_training_inputs(f"data/scenes/{scene}", f"data/init/{scene}", f"data/priors/{scene}", cfg, loss)
tr = T.Trainer(p, views, cfg, loss, resolve_backend(cfg.backend))
for _ in range(3): tr.step()
tr.it = 425
for _ in range(len(tr.queue) + views.num_views): tr.step()
fw, bw = {}, {}
for rep in range(30):
    it = tr.it; i = tr._next_view()
    full = tr.views.at(i, cfg.downscale_at(it)); v = full
    out = rasterize(tr.params.surfels(min(cfg.sh_degree, it // cfg.sh_every)), v.camera, tr.backend)
    tr._remember_depth(i, full, None, out.depth_median.detach() * (out.alpha.detach() > cfg.surface_alpha))
    rgb = out.features.permute(2, 0, 1) + cfg.background * (1.0 - out.alpha)
    target = T.masked_target(v, cfg.background)
    maps = [out.features, out.alpha, out.depth_expected, out.depth_median, out.normal_cam, out.distortion]
    t = time.perf_counter()
    terms = []
    for name, value, weight in tr.loss_terms(it, i, v, out, rgb, target, full, None):
        t2 = time.perf_counter(); fw.setdefault(name, []).append(t2 - t); t = t2
        if weight is not None: terms.append((name, value * weight))
    for name, value in terms:
        t = time.perf_counter()
        torch.autograd.grad(value, [m for m in maps], retain_graph=True, allow_unused=True)
        bw.setdefault(name, []).append(time.perf_counter() - t)
    # the rasterizer's own backward, with every map's cotangent
    t = time.perf_counter()
    torch.autograd.backward(maps, [torch.ones_like(m) for m in maps])
    bw.setdefault("rasterizer", []).append(time.perf_counter() - t)
    for q in tr.params.tensors().values(): q.grad = None
    tr.it += 1
print("term, forward ms (median), backward to the maps ms (median)")
for k in list(fw) + ["rasterizer"]:
    f = statistics.median(fw[k]) * 1e3 if k in fw else float("nan")
    b = statistics.median(bw[k]) * 1e3 if k in bw else float("nan")
    print(f"{k:10s} {f:7.2f} {b:7.2f}")
