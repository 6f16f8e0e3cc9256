"""A `fast` training of SCENE with L_smooth and L_dn from torch or from the prototype kernels (smooth_kernel.py, dn_kernel.py): the
parameters saved to OUT, the wall time and the trainer's split printed. Run from the checkout:
python experiments/loss_terms_2026-12-06/train_ab.py torch|kernels SCENE OUT.pt"""
import sys, time, importlib, importlib.util, torch
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import load_params, section
from pipeline.rasterizer import resolve_backend
from pipeline.runs.optimize import load_training_inputs
T = importlib.import_module("pipeline.optimize.train")
mode, scene, out = sys.argv[1], sys.argv[2], sys.argv[3]
if mode == "kernels":  # both prototypes in the torch terms' places, compiled before the timed steps
    spec = importlib.util.spec_from_file_location("sk", "experiments/loss_terms_2026-12-06/smooth_kernel.py")
    sk = importlib.util.module_from_spec(spec); spec.loader.exec_module(sk)
    T.normal_smoothness_loss = sk.smooth_fused
    spec = importlib.util.spec_from_file_location("dk", "experiments/loss_terms_2026-12-06/dn_kernel.py")
    dk = importlib.util.module_from_spec(spec); spec.loader.exec_module(dk)
    T.depth_normal_loss = dk.dn_fused
    _n = torch.randn(8, 8, 3, requires_grad=True).permute(2, 0, 1)
    dk.dn_fused(_n, torch.rand(8, 8, requires_grad=True) + 1, torch.rand(8, 8), torch.eye(3)).backward()
    _n = torch.randn(8, 8, 3, requires_grad=True).permute(2, 0, 1)  # compile the kernels (the renders' layout) outside the timed steps
    sk.smooth_fused(_n, torch.rand(3, 8, 8), torch.ones(8, 8, dtype=torch.bool), 10.0).backward()
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
