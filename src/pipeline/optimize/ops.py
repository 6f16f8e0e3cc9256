"""Surfel set edits that keep the Adam state consistent (as gsplat's ``strategy/ops.py``).

Each parameter is its own optimizer group holding exactly one tensor. An edit builds new
leaf tensors, swaps them into the groups and carries the moments along: kept surfels keep
their moments, new surfels start at zero (2DGS/gsplat), so no surfel ever inherits another
one's momentum and the optimizer never sees a tensor it does not know.
"""
from __future__ import annotations

from collections.abc import Callable

import torch

from pipeline.optimize.surfels import PARAM_NAMES, SurfelParams


def make_optimizer(params: SurfelParams, lrs: dict[str, float], eps: float = 1e-15) -> torch.optim.Adam:
    """Adam with one group per parameter (named), learning rates from ``lrs``."""
    groups = [{"params": [getattr(params, k)], "lr": lrs[k], "name": k} for k in PARAM_NAMES]
    return torch.optim.Adam(groups, lr=0.0, eps=eps, fused=True)  # one pass per tensor (CPU kernel)


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
