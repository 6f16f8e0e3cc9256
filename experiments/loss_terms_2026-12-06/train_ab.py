"""A `fast` training of SCENE with L_smooth and L_dn from the library (on the CPU its kernels,
``losses._smooth_kernels`` / ``_dn_kernels``) or from the torch compositions beside them: the
parameters saved to OUT, the loop's wall time and the trainer's split printed. Run from the
checkout: python experiments/loss_terms_2026-12-06/train_ab.py torch|kernels SCENE OUT.pt
(The prototypes' version of this script, which patched them in, is in git history: 04d6c2b.)"""
import sys, time, importlib, torch
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.rasterizer import resolve_backend
from pipeline.runs.optimize import load_training_inputs
from pipeline.losses.smoothness import _normal_smoothness_torch
from pipeline.losses.normal import _depth_normal_loss_torch
T = importlib.import_module("pipeline.optimize.train")
mode, scene, out = sys.argv[1], sys.argv[2], sys.argv[3]
if mode == "torch":
    T.normal_smoothness_loss = lambda n, i, v, g: _normal_smoothness_torch(n, i.detach(), v, g)
    T.depth_normal_loss = _depth_normal_loss_torch
params = load_params("params.yaml")
cfg, loss = section(OptimizeConfig, "optimize", params), section(LossConfig, "loss", params)
_, p, views = load_training_inputs(f"data/scenes/{scene}", f"data/init/{scene}", f"data/priors/{scene}", cfg, loss)
tr = T.Trainer(p, views, cfg, loss, resolve_backend(cfg.backend))
tr.step()
t = time.perf_counter()
while tr.it < cfg.iterations:
    tr.step()
wall = time.perf_counter() - t
torch.save({k: v.detach().clone() for k, v in tr.params.tensors().items()}, out)
print(mode, scene, f"wall {wall:.2f} s", {k: round(v, 2) for k, v in tr.seconds.items() if v > 0.05})
