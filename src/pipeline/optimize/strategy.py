"""Adaptive density control of the surfels as a strategy object with explicit state
(after gsplat's ``DefaultStrategy`` and 2DGS's ``densify_and_prune``).

* The screen-space gradient is the gradient of the loss w.r.t. each splat's projected
  centre. Every rasterizer backend returns it in pixels; :func:`screen_grad_ndc` turns it
  into normalised device units (x W/2, x H/2, as gsplat does), the one place where that
  happens, so a threshold means the same on the cpu and cuda backends and at every
  training resolution.
* Sizes are in the normalised frame, relative to ``scene_extent`` (the object's radius,
  1 for the unit sphere of scale_mat).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from pipeline.config.optimize import DensifyConfig
from pipeline.optimize import ops
from pipeline.optimize.region import SurfelRegion
from pipeline.surfels import SurfelParams


def screen_grad_ndc(means2d_grad: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Norm of the screen-space gradient in normalised device units, ``(P,)``."""
    g = means2d_grad.detach()
    scale = torch.tensor([width / 2.0, height / 2.0], dtype=g.dtype)
    return (g * scale).norm(dim=1).to(torch.float64)


@dataclass
class DensifyState:
    """Accumulators since the last refinement, one entry per surfel."""

    grad2d: torch.Tensor  # (P,) summed NDC gradient norms
    count: torch.Tensor  # (P,) renders in which the surfel was visible
    max_radii: torch.Tensor  # (P,) largest screen radius seen, in units of max(W, H)

    @classmethod
    def zeros(cls, n: int) -> DensifyState:
        z = torch.zeros(n, dtype=torch.float64)
        return cls(z.clone(), z.clone(), z.clone())

    def select(self, keep: torch.Tensor) -> None:
        self.grad2d, self.count, self.max_radii = self.grad2d[keep], self.count[keep], self.max_radii[keep]

    def extend(self, n: int) -> None:
        z = torch.zeros(n, dtype=torch.float64)
        self.grad2d, self.count, self.max_radii = (torch.cat([t, z]) for t in (self.grad2d, self.count, self.max_radii))

    def state_dict(self) -> dict:
        return {"grad2d": self.grad2d, "count": self.count, "max_radii": self.max_radii}


@dataclass
class DensifyStrategy:
    """Clone small / split large surfels with a high mean screen-space gradient, prune
    transparent and oversized ones, reset opacities periodically; all under a surfel
    budget (``max_surfels``, the scene's: :func:`pipeline.optimize.region.surfel_budget`;
    None: ``cfg.max_surfels``) and inside ``region`` (None: anywhere): surfels outside it
    are neither cloned nor split, and each refinement prunes those outside, split children
    included. ``cfg`` is the rest of its configuration (params ``optimize.densify``),
    ``state`` its accumulators. Iteration numbers are 0-based steps of the training loop."""

    cfg: DensifyConfig
    scene_extent: float = 1.0
    max_surfels: int | None = None
    region: SurfelRegion | None = None
    state: DensifyState | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        if self.max_surfels is None:
            self.max_surfels = self.cfg.max_surfels

    def initialize(self, num: int) -> None:
        self.state = DensifyState.zeros(num)

    def step_post_backward(self, params: SurfelParams, means2d_grad: torch.Tensor | None, radii: torch.Tensor,
                           width: int, height: int) -> None:
        """Accumulate the statistics of one render (call after ``backward``)."""
        if means2d_grad is None:
            return
        visible = radii > 0  # masked sums, not boolean indexing: no nonzero() and gathers per step
        self.state.grad2d += torch.where(visible, screen_grad_ndc(means2d_grad, width, height), 0.0)
        self.state.count += visible
        r = radii.to(torch.float64) / max(width, height)
        self.state.max_radii = torch.maximum(self.state.max_radii, torch.where(visible, r, 0.0))

    def refines_at(self, it: int) -> bool:
        """Whether iteration ``it`` densifies and prunes. Not within ``every`` steps after an
        opacity reset (as gsplat's pause_refine_after_reset): every surfel would look
        transparent and be pruned."""
        since_reset = it % self.cfg.reset_every if self.cfg.reset_every > 0 else it
        return (self.cfg.start_iter <= it < self.cfg.stop_iter and it > 0 and it % self.cfg.every == 0
                and (it < self.cfg.reset_every or since_reset >= self.cfg.every))

    def step_post_update(self, params: SurfelParams, optimizer: torch.optim.Optimizer, it: int,
                         generator: torch.Generator) -> dict:
        """Refine after the optimizer step of iteration ``it``; returns what changed."""
        done = {}
        if self.refines_at(it):
            done.update(self._densify(params, optimizer, generator))
            after_reset = self.cfg.reset_every > 0 and it > self.cfg.reset_every
            done.update(self._prune(params, optimizer, after_reset=after_reset))
            self.state = DensifyState.zeros(params.num)
        if self.cfg.reset_every > 0 and it > 0 and it % self.cfg.reset_every == 0 and it < self.cfg.stop_iter:
            with torch.no_grad():
                cap = torch.logit(torch.tensor(self.cfg.reset_value, dtype=params.opacity_logits.dtype))
                ops.set_values(params, optimizer, "opacity_logits", params.opacity_logits.clamp_max(cap))
            done["reset"] = True
        return done

    def _densify(self, params: SurfelParams, optimizer, generator) -> dict:
        grads = self.state.grad2d / self.state.count.clamp_min(1)
        high = grads >= self.cfg.grad_threshold
        if self.region is not None:
            high &= self.region.contains(params.means)
        with torch.no_grad():
            max_scale = torch.exp(params.log_scales.max(dim=1).values).to(torch.float64)
        small = max_scale <= self.cfg.percent_dense * self.scene_extent
        clone, split = high & small, high & ~small
        room = self.max_surfels - params.num
        # Under the budget: the surfels with the largest gradients go first.
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone + n_split > room:
            order = torch.argsort(torch.where(high, grads, -1.0), descending=True)
            allowed = torch.zeros_like(high)
            allowed[order[: max(room, 0)]] = True
            clone, split = clone & allowed, split & allowed
            n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            ops.duplicate(params, optimizer, self.state, clone)
            split = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool)])
        if n_split:
            ops.split(params, optimizer, self.state, split, self.cfg.split_factor, generator)
        return {"cloned": n_clone, "split": n_split}

    def _prune(self, params: SurfelParams, optimizer, after_reset: bool) -> dict:
        with torch.no_grad():
            prune = torch.sigmoid(params.opacity_logits).to(torch.float64) < self.cfg.prune_opacity
            if after_reset:
                prune |= torch.exp(params.log_scales.max(dim=1).values).to(torch.float64) > (
                    self.cfg.max_world_scale * self.scene_extent)
                if self.cfg.max_screen_fraction > 0:
                    prune |= self.state.max_radii > self.cfg.max_screen_fraction
        outside = ~self.region.contains(params.means) if self.region is not None else torch.zeros_like(prune)
        prune |= outside
        if prune.all():  # never prune to nothing: a scene of zero surfels cannot recover
            prune[torch.argmax(params.opacity_logits.detach())] = False
        n = int(prune.sum())
        if n:
            ops.select(params, optimizer, ~prune)
            self.state.select(~prune)
        return {"pruned": n, "outside": int(outside.sum())}
