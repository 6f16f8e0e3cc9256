"""Surfel set edits that keep the Adam state consistent (as gsplat's ``strategy/ops.py``).

Each parameter is its own optimizer group holding exactly one tensor. An edit builds new
leaf tensors, swaps them into the groups and carries the moments along: kept surfels keep
their moments, new surfels start at zero (2DGS/gsplat), so no surfel ever inherits another
one's momentum and the optimizer never sees a tensor it does not know.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import torch

from pipeline.rasterizer.project import quat_to_rotmat
from pipeline.surfels import PARAM_NAMES, SurfelParams

if TYPE_CHECKING:
    from pipeline.optimize.strategy import DensifyState


def make_optimizer(params: SurfelParams, lrs: dict[str, float], betas: tuple[float, float],
                   eps: float = 1e-15) -> torch.optim.Adam:
    """Adam with one group per parameter (named), learning rates from ``lrs``, moments' decay
    ``betas`` (``optimize.adam_betas``)."""
    groups = [{"params": [getattr(params, k)], "lr": lrs[k], "name": k} for k in PARAM_NAMES]
    return torch.optim.Adam(groups, lr=0.0, betas=betas, eps=eps, fused=True)  # one pass per tensor (CPU kernel)


def _swap(params: SurfelParams, optimizer: torch.optim.Optimizer,
          param_fn: Callable[[str, torch.Tensor], torch.Tensor],
          state_fn: Callable[[str, str, torch.Tensor], torch.Tensor]) -> None:
    new = {}
    for group in optimizer.param_groups:
        name = group["name"]
        old = group["params"][0]
        p = torch.nn.Parameter(param_fn(name, old.detach())).requires_grad_(True)
        state = optimizer.state.pop(old, None)
        if state:
            for key, v in list(state.items()):
                if key != "step" and torch.is_tensor(v) and v.shape == old.shape:
                    state[key] = state_fn(name, key, v)
            optimizer.state[p] = state
        group["params"][0] = p
        new[name] = p
    params.replace(new)


def select(params: SurfelParams, optimizer: torch.optim.Optimizer, keep: torch.Tensor) -> None:
    """Keep the surfels where the bool mask ``keep`` is True (with their moments)."""
    _swap(params, optimizer, lambda n, p: p[keep], lambda n, k, v: v[keep])


def append(params: SurfelParams, optimizer: torch.optim.Optimizer, new: dict[str, torch.Tensor]) -> None:
    """Append surfels (values per parameter name); their moments start at zero."""
    _swap(params, optimizer, lambda n, p: torch.cat([p, new[n].to(p)]),
          lambda n, k, v: torch.cat([v, torch.zeros((len(new[n]),) + v.shape[1:], dtype=v.dtype)]))


def set_values(params: SurfelParams, optimizer: torch.optim.Optimizer, name: str, values: torch.Tensor,
               reset_state: bool = True) -> None:
    """Overwrite one parameter (e.g. the opacity reset); its moments restart at zero."""
    _swap(params, optimizer, lambda n, p: values.to(p) if n == name else p,
          lambda n, k, v: torch.zeros_like(v) if (n == name and reset_state) else v)


def duplicate(params: SurfelParams, optimizer: torch.optim.Optimizer, state: DensifyState,
              mask: torch.Tensor) -> None:
    """Append a copy of each surfel where ``mask`` (moments at zero, statistics at zero)."""
    with torch.no_grad():
        new = {k: v[mask].detach().clone() for k, v in params.tensors().items()}
    append(params, optimizer, new)
    state.extend(int(mask.sum()))


def split(params: SurfelParams, optimizer: torch.optim.Optimizer, state: DensifyState, mask: torch.Tensor,
          factor: float, generator: torch.Generator) -> None:
    """Replace each surfel where ``mask`` by two children, centres drawn from its 2D Gaussian
    in its own plane, scales divided by ``factor`` (2DGS)."""
    n = int(mask.sum())
    with torch.no_grad():
        src = {k: v[mask].detach() for k, v in params.tensors().items()}
        s = torch.exp(src["log_scales"])
        R = quat_to_rotmat(src["quats"])
        children = []
        for _ in range(2):
            uv = torch.randn(s.shape, generator=generator, dtype=torch.float64).to(s) * s
            offset = (R[:, :, :2] @ uv.unsqueeze(-1)).squeeze(-1)
            child = dict(src)
            child["means"] = src["means"] + offset
            child["log_scales"] = torch.log(s / factor)
            children.append(child)
        new = {k: torch.cat([c[k] for c in children]) for k in src}
    append(params, optimizer, new)
    state.extend(2 * n)
    keep = torch.cat([~mask, torch.ones(2 * n, dtype=torch.bool)])
    select(params, optimizer, keep)
    state.select(keep)
