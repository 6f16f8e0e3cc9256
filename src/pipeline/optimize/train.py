"""The GCGS training loop (docs/optimize.md): 2D Gaussian surfels fitted to the input views
in the normalised frame with

    L = L_photo + lambda_gcf L_gcf + lambda_nor (lambda_nc L_nc + lambda_ngc L_ngc)
        + lambda_mvs L_mvs + lambda_d L_d + lambda_dn L_dn + lambda_mask L_mask

(GCGS Eq. 13 plus 2DGS's depth-normal consistency L_dn and, where masks are used, the
alpha-vs-mask term). One input view per iteration, in a seeded shuffled order; that view
is the reference of L_gcf, the other input views its sources.

Robustness: every term is checked for finiteness before the backward pass (a non-finite
one stops training with its name and iteration); surfels with non-finite gradients or
parameters, or a scale outside ``[MIN_SCALE, MAX_SCALE x extent]``, are removed before
the optimizer step can spread them. A checkpoint (parameters, Adam moments, densification
state, random states, view queue) is written every ``checkpoint_every`` iterations; a
resumed run ends bitwise equal to an uninterrupted one on the deterministic cpu backend.
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from pipeline import atomic
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.errors import ConfigError, Interrupted
from pipeline.losses import (
    SourceView,
    best_source_ncc,
    depth_normal_loss,
    flat_pixels,
    gcf_loss,
    mask_loss,
    multiview_consistency,
    mvs_depth_loss,
    normal_consistency_losses,
    normal_smoothness_loss,
    photometric_loss,
    reference_pixels,
    textured_pixels,
)
from pipeline.optimize import ops
from pipeline.optimize.photoreset import visible_surfels_at
from pipeline.optimize.region import region_from_views, surfel_budget
from pipeline.optimize.strategy import DensifyState, DensifyStrategy
from pipeline.optimize.views import TrainViews, ViewData, crop_view, crop_window
from pipeline.rasterizer import rasterize, resolve_backend
from pipeline.surfels import SurfelParams

MIN_SCALE = 1e-8  # normalised units; below, a surfel is degenerate (zero area)
MAX_SCALE = 10.0  # x scene_extent; above, a surfel covers everything (degenerate)
TIMED = ("render", "photo", "gcf", "mv", "nor", "mvs", "dn", "dist", "mask", "backward", "step", "densify",
         "photo_reset", "smooth")

CHECKPOINT_KIND = "checkpoint"  # the kind its checkpoint files carry (pipeline.atomic): only those are resumed or deleted


class NonFiniteLossError(RuntimeError):
    """A loss term became NaN or Inf; training stopped and no model was written."""


@dataclass
class TrainResult:
    params: SurfelParams
    iterations: int
    backend: str
    num_init: int
    history: list[dict] = field(default_factory=list)  # one row per logged iteration
    seconds: dict = field(default_factory=dict)  # summed time per part of an iteration
    removed_degenerate: int = 0
    removed_outside: int = 0  # surfels pruned outside the region (optimize.region), the final prune included
    surfel_budget: dict = field(default_factory=dict)  # the scene's budget and the rule that set it
    resumed_from: int | None = None
    final_terms: dict = field(default_factory=dict)
    # Wall and CPU seconds of the training loop in earlier runs of this training (those up
    # to the checkpoint resumed from; zero for a fresh run), so a resumed run reports what
    # the whole training cost.
    spent_before: dict = field(default_factory=lambda: {"wall_s": 0.0, "cpu_s": 0.0})


def _fingerprint(cfg: OptimizeConfig, loss: LossConfig, params0: SurfelParams, views: TrainViews) -> str:
    h = hashlib.sha256()
    h.update(json.dumps([asdict(cfg), asdict(loss), views.scene.view_ids], sort_keys=True, default=str).encode())
    for t in params0.tensors().values():
        h.update(t.detach().numpy().tobytes())
    return h.hexdigest()[:16]


def _lrs(cfg: OptimizeConfig) -> dict[str, float]:
    lrs = asdict(cfg.lr)
    lrs["means"] = cfg.lr.means * cfg.scene_extent
    lrs.pop("means_final")
    return lrs


def _means_lr(cfg: OptimizeConfig, it: int) -> float:
    t = min(max(it / max(cfg.iterations - 1, 1), 0.0), 1.0)
    return cfg.scene_extent * math.exp((1 - t) * math.log(cfg.lr.means) + t * math.log(cfg.lr.means_final))


class Trainer:
    """Holds the whole training state, so that a checkpoint is one ``state_dict``."""

    def __init__(self, params: SurfelParams, views: TrainViews, cfg: OptimizeConfig, loss: LossConfig,
                 backend: str = "cpu"):
        if 0 < cfg.crop.fraction < 1 and loss.lambda_gcf > 0:
            raise ConfigError("optimize.crop.fraction < 1 needs loss.lambda_gcf 0: L_gcf's feature maps are not cut "
                              "to the crop")
        self.cfg, self.loss, self.views = cfg, loss, views
        self.backend = backend
        self.params = params
        self.num_init = params.num
        self.fingerprint = _fingerprint(cfg, loss, params, views)
        self.optimizer = ops.make_optimizer(params, _lrs(cfg), tuple(cfg.adam_betas))
        masks = views.training_masks()
        self.region = region_from_views(views.scene, masks, cfg)
        self.budget = surfel_budget(views.scene, masks, cfg)
        self.strategy = DensifyStrategy(cfg.densify, scene_extent=cfg.scene_extent, max_surfels=self.budget.surfels,
                                        region=self.region)
        self.strategy.initialize(params.num)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.queue: list[int] = []
        # Each view's last rendered depth (detached) and its intrinsics: the forward-backward
        # check of L_mv reads the source views' depth from when they were last rendered
        # (at most num_views - 1 iterations old) instead of rendering them again.
        self.last_depth: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        # L_smooth's flat pixels per (view, size): they depend on the image alone (_flat).
        self.flat_cache: dict[tuple[int, tuple[int, int]], torch.Tensor] = {}
        self.textured_cache: dict[tuple[int, tuple[int, int]], torch.Tensor] = {}
        self.it = 0
        self.removed_degenerate = 0
        self.removed_outside = 0
        self.seconds: dict[str, float] = defaultdict(float)
        self.spent = {"wall_s": 0.0, "cpu_s": 0.0}  # the training loop's time, over every run

    # -- checkpoints -------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "fingerprint": self.fingerprint, "it": self.it, "num_init": self.num_init,
            "params": {k: v.detach().clone() for k, v in self.params.tensors().items()},
            "optimizer": self.optimizer.state_dict(), "strategy": self.strategy.state.state_dict(),
            "generator": self.generator.get_state(), "rng": self.rng.bit_generator.state,
            "queue": list(self.queue), "removed_degenerate": self.removed_degenerate,
            "removed_outside": self.removed_outside,
            "seconds": dict(self.seconds), "spent": dict(self.spent),
            "last_depth": {k: (d.clone(), K.clone()) for k, (d, K) in self.last_depth.items()},
        }

    def load_state_dict(self, state: dict) -> None:
        if state["fingerprint"] != self.fingerprint:
            raise ValueError("checkpoint belongs to another configuration or input")
        self.params.replace({k: v.clone().requires_grad_(True) for k, v in state["params"].items()})
        self.optimizer = ops.make_optimizer(self.params, _lrs(self.cfg), tuple(self.cfg.adam_betas))
        self.optimizer.load_state_dict(state["optimizer"])
        self.strategy.state = DensifyState(**state["strategy"])
        self.generator.set_state(state["generator"])
        self.rng.bit_generator.state = state["rng"]
        self.queue = list(state["queue"])
        self.it = int(state["it"])
        self.num_init = int(state["num_init"])
        self.removed_degenerate = int(state["removed_degenerate"])
        self.removed_outside = int(state["removed_outside"])
        self.seconds = defaultdict(float, state["seconds"])
        self.spent = dict(state["spent"])
        self.last_depth = dict(state.get("last_depth", {}))

    def save_checkpoint(self, path: Path) -> None:
        with atomic.atomic_file(path, kind=CHECKPOINT_KIND) as tmp:
            torch.save(self.state_dict(), tmp)

    def try_resume(self, path: Path, log: Callable[[str], None]) -> bool:
        if not path.is_file():
            return False
        try:
            state = torch.load(path, weights_only=False)
            self.load_state_dict(state)
        except Exception as exc:  # a stale or broken checkpoint is not fatal: start over
            log(f"ignoring checkpoint {path}: {exc}")
            return False
        log(f"resumed from {path} at iteration {self.it}")
        return True

    # -- one iteration -------------------------------------------------------------
    def _next_view(self) -> int:
        if not self.queue:
            self.queue = [int(i) for i in self.rng.permutation(self.views.num_views)]
        return self.queue.pop()

    def step(self) -> dict:
        cfg, it = self.cfg, self.it
        clock = time.perf_counter
        t = clock()
        for group in self.optimizer.param_groups:
            if group["name"] == "means":
                group["lr"] = _means_lr(cfg, it)
        i = self._next_view()
        full = self.views.at(i, cfg.downscale_at(it))
        window = crop_window(full.size, cfg.crop.fraction, full.mask, self.generator) if cfg.crop.active_at(it) else None
        v = full if window is None else crop_view(full, *window)
        h, w = v.size
        degree = min(cfg.sh_degree, it // cfg.sh_every)
        out = rasterize(self.params.surfels(degree), v.camera, self.backend)
        if self.loss.lambda_mv > 0 or self.loss.lambda_mvgeo > 0:
            self._remember_depth(i, full, window, out.depth_median.detach() * (out.alpha.detach() > cfg.surface_alpha))
        rgb = out.features.permute(2, 0, 1) + cfg.background * (1.0 - out.alpha)
        target = masked_target(v, cfg.background)
        t2 = clock()
        self.seconds["render"] += t2 - t

        values: dict[str, torch.Tensor] = {}
        total = torch.zeros((), dtype=rgb.dtype)
        for name, value, weight in self.loss_terms(it, i, v, out, rgb, target, full, window):
            if weight is None:  # logged only
                values[name] = value.detach()
                continue
            if not bool(torch.isfinite(value)):
                raise NonFiniteLossError(f"loss term {name} is {float(value.detach())} at iteration {it} "
                                         f"(view {v.view_id}, {self.params.num} surfels); no model written")
            values[name] = value.detach()
            total = total + weight * value
            t3 = clock()
            self.seconds[name] += t3 - t2  # each term's own time: the generator computes it on demand
            t2 = t3
        values["total"] = total.detach()

        t = clock()
        total.backward()
        t2 = clock()
        self.seconds["backward"] += t2 - t
        bad = self._degenerate()
        if bad.any():
            for p in self.params.tensors().values():
                if p.grad is not None:
                    p.grad[bad] = 0.0
        # The densification statistic as the whole view would give it: screen units of the whole
        # view, and the crop's mean losses weighted by its share of the view's pixels (the part
        # of the whole view's mean loss its pixels make), or a crop densifies 1/share too much.
        grad2d = out.means2d.grad
        if window is not None and grad2d is not None:
            grad2d = grad2d * (w * h / (full.size[0] * full.size[1]))
        self.strategy.step_post_backward(self.params, grad2d, out.radii, full.size[1], full.size[0])
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        bad |= self._degenerate()
        if bad.any():
            self._remove(bad)
        t = clock()
        self.seconds["step"] += t - t2
        refine = self.strategy.refines_at(it)
        changes = self.strategy.step_post_update(self.params, self.optimizer, it, self.generator)
        self.removed_outside += changes.get("outside", 0)
        t2 = clock()
        self.seconds["densify"] += t2 - t
        # After the step's pruning, so a reset surfel has until the next one to earn its
        # opacity back (it is pruned then if it has not).
        if cfg.photo_reset.enabled and refine:
            changes["photo_reset"] = self._photo_reset(it)
            self.seconds["photo_reset"] += clock() - t2
        self.it += 1
        row = {"iteration": it, "view": v.view_id, "width": w, "height": h, "surfels": self.params.num}
        row.update({k: float(x) for k, x in values.items()})
        row.update({k: int(x) for k, x in changes.items()})
        return row

    def loss_terms(self, it: int, i: int, v, out, rgb: torch.Tensor, target: torch.Tensor, full: ViewData,
                   window: tuple[int, int, int, int] | None) -> Iterator[tuple[str, torch.Tensor, float | None]]:
        """The named, weighted loss terms of iteration ``it`` on view ``i`` (render ``out``,
        composited ``rgb``, ``target`` image), in a fixed order, each computed when asked for
        (so the caller times each); a weight of ``None`` is a figure logged, not optimised.
        ``v`` is the whole view ``full``, or its window ``window`` ``(x0, y0, w, h)`` when
        training on a crop (``window`` ``None``: no crop)."""
        cfg, lw = self.cfg, self.loss
        photo, l1 = photometric_loss(rgb, target, lw.lambda_dssim)
        yield "photo", photo, 1.0
        yield "l1", l1, None
        surface = out.alpha.detach() > cfg.surface_alpha
        if v.mask is not None:
            surface &= v.mask
        if lw.lambda_gcf > 0 and it >= cfg.start.gcf and v.features is not None:
            sources = [(s.K, s.world_to_cam, s.features, s.feature_image_size)
                       for j in range(self.views.num_views) if j != i
                       for s in [self.views.at(j, cfg.downscale_at(it))]]
            points = surface
            n_surface = int(surface.sum())
            if 0 < cfg.gcf_max_points < n_surface:  # a random subset: the loss is a mean over points
                idx = torch.nonzero(surface.reshape(-1)).squeeze(1)
                pick = idx[torch.randperm(n_surface, generator=self.generator)[: cfg.gcf_max_points]]
                points = torch.zeros(surface.numel(), dtype=torch.bool)
                points[pick] = True
                points = points.view_as(surface)
            yield "gcf", gcf_loss(out.depth_expected, v.K, v.world_to_cam, v.features, sources, valid=points,
                                  ref_image_size=v.feature_image_size,
                                  max_dissimilarity=lw.gcf_max_dissimilarity), lw.lambda_gcf
        if (lw.lambda_mv > 0 or lw.lambda_mvgeo > 0) and it >= cfg.start.mv:
            maps = (out.depth_median, out.normal_cam, surface)
            if window is not None:  # L_mv works in the whole view's pixels
                maps = tuple(_uncrop(x, window, full.size) for x in maps)
            mv = self._multiview(i, full.K, *maps)
            yield "mv", mv["photo"], lw.lambda_mv
            yield "mvgeo", mv["geo"], lw.lambda_mvgeo
            yield "mv_valid", mv["valid_fraction"], None
        if lw.lambda_smooth > 0 and it >= cfg.start.mv:
            where = surface & self._flat(i, full, window) if lw.smooth_max_std > 0 else surface
            yield "smooth", normal_smoothness_loss(out.normal_cam.permute(2, 0, 1), target, where,
                                                   lw.smooth_gamma), lw.lambda_smooth
        if lw.lambda_nor > 0 and it >= cfg.start.nor and v.normal_prior is not None:
            n_hat = F.normalize(out.normal_cam, dim=2).permute(2, 0, 1)
            l_nc, l_ngc = normal_consistency_losses(n_hat, v.normal_prior, v.normal_valid & surface)
            yield "nor", lw.lambda_nc * l_nc + lw.lambda_ngc * l_ngc, lw.lambda_nor
        if lw.lambda_mvs > 0 and v.mvs_depth is not None:
            t = it / max(cfg.iterations - 1, 1)
            yield "mvs", mvs_depth_loss(out.depth_median, v.mvs_depth, surface & (v.mvs_depth > 0)), \
                lw.lambda_mvs * (1.0 - t * (1.0 - lw.mvs_final))
        if lw.lambda_dn > 0 and it >= cfg.start.dn:
            depth = out.depth_median if cfg.dn_depth == "median" else out.depth_expected
            yield "dn", depth_normal_loss(out.normal_cam.permute(2, 0, 1), depth, out.alpha, v.K), lw.lambda_dn
        if lw.lambda_d > 0 and it >= cfg.start.d:
            yield "dist", out.distortion.mean(), lw.lambda_d
        if lw.lambda_mask > 0 and v.mask is not None:
            yield "mask", mask_loss(out.alpha, v.mask), lw.lambda_mask

    def _multiview(self, i: int, K_train: torch.Tensor, depth: torch.Tensor, normal: torch.Tensor,
                   surface: torch.Tensor) -> dict[str, torch.Tensor]:
        """L_mv's photometric and geometric parts on a seeded random subset of the ``surface``
        pixels of view ``i`` (rendered ``depth``, ``normal`` at intrinsics ``K_train``) seen
        within ``loss.mv_max_incidence_deg`` of the ray, the other input views as sources
        (:mod:`pipeline.losses.multiview`)."""
        cfg, lw, views = self.cfg, self.loss, self.views
        candidates = reference_pixels(surface, normal, K_train, lw.mv_max_incidence_deg)
        if cfg.mv_textured_points:
            candidates &= self._textured(i, surface.shape)
        ys, xs = torch.nonzero(candidates, as_tuple=True)
        if 0 < cfg.mv_max_points < len(xs):
            pick = torch.randperm(len(xs), generator=self.generator)[: cfg.mv_max_points]
            ys, xs = ys[pick], xs[pick]
        K_full = torch.from_numpy(views.scene.K[i]).float()
        return multiview_consistency(depth, normal, torch.stack([xs, ys], 1), K_train, K_full,
                                     views.grey_full[i], self._sources(i, self.last_depth), patch=lw.mv_patch,
                                     min_patch_std=lw.mv_min_patch_std, max_fb_px=lw.mv_max_fb_px,
                                     ncc_gamma=lw.mv_ncc_gamma, best_sources=lw.mv_best_sources,
                                     max_cost=lw.mv_max_cost)

    def _textured(self, i: int, size: tuple[int, int]) -> torch.Tensor:
        """:func:`pipeline.losses.multiview.textured_pixels` of view ``i`` at the training
        ``size`` (h, w), once per (view, size): L_mv samples its points among them, since a
        flat reference patch gives no pair (on synth_textureless 68-73% of the masked pixels
        are flat)."""
        key = (i, tuple(size))
        if key not in self.textured_cache:
            lw = self.loss
            self.textured_cache[key] = textured_pixels(self.views.grey_full[i], size[0], size[1], lw.mv_patch,
                                                       lw.mv_min_patch_std, lw.mv_ncc_gamma)
        return self.textured_cache[key]

    def _flat(self, i: int, full: ViewData, window: tuple[int, int, int, int] | None) -> torch.Tensor:
        """:func:`pipeline.losses.smoothness.flat_pixels` of view ``i``'s masked target at
        ``full``'s size, computed once per (view, size) since nothing training changes moves
        it. It is taken on the whole view, so a crop's border pixels keep their whole
        neighbourhood; ``window`` ``(x0, y0, w, h)`` cuts it to the crop."""
        key = (i, full.size)
        if key not in self.flat_cache:
            self.flat_cache[key] = flat_pixels(masked_target(full, self.cfg.background), self.loss.smooth_max_std)
        flat = self.flat_cache[key]
        if window is None:
            return flat
        x0, y0, w, h = window
        return flat[y0:y0 + h, x0:x0 + w]

    def _remember_depth(self, i: int, full: ViewData, window: tuple[int, int, int, int] | None,
                        depth: torch.Tensor) -> None:
        """Keep view ``i``'s rendered surface depth (detached) for L_mv's forward-backward check
        of later iterations: the whole map, or a crop's window written into the last one
        (outside it the depth stays from when it was last rendered, or none)."""
        if window is None:
            self.last_depth[i] = (depth, full.K)
            return
        x0, y0, w, h = window
        prev = self.last_depth.get(i)
        whole = prev[0].clone() if prev is not None and tuple(prev[0].shape) == full.size else \
            torch.zeros(full.size, dtype=depth.dtype)
        whole[y0:y0 + h, x0:x0 + w] = depth
        self.last_depth[i] = (whole, full.K)

    def _sources(self, i: int, depths: dict[int, tuple[torch.Tensor, torch.Tensor]]) -> list[SourceView]:
        """The other input views as sources of view ``i`` (full-resolution grey images),
        each with its rendered depth and intrinsics from ``depths`` when it holds them."""
        views = self.views
        ref_from = torch.from_numpy(np.linalg.inv(views.w2c_norm[i]))
        sources = []
        for j in range(views.num_views):
            if j == i:
                continue
            w2c_j = torch.from_numpy(views.w2c_norm[j])
            depth_j, K_j = depths.get(j, (None, None))
            sources.append(SourceView(K_full=torch.from_numpy(views.scene.K[j]).float(),
                                      ref_to_src=(w2c_j @ ref_from).float(), grey_full=views.grey_full[j],
                                      depth_train=depth_j, K_train=K_j))
        return sources

    @torch.no_grad()
    def _photo_reset(self, it: int) -> int:
        """Cap the opacity of the surfels that are the visible surface of a textured pixel
        whose rendered plane matches no other input view that sees it (``optimize.photo_reset``,
        at the training resolution of ``it``). Returns how many were reset."""
        cfg, lw, views = self.cfg, self.loss, self.views
        pr = cfg.photo_reset
        factor = cfg.downscale_at(it)
        surf = self.params.surfels(min(cfg.sh_degree, it // cfg.sh_every))
        renders, depths = [], {}
        for i in range(views.num_views):
            v = views.at(i, factor)
            out = rasterize(surf, v.camera, self.backend)
            surface = out.alpha > cfg.surface_alpha
            if v.mask is not None:
                surface &= v.mask
            renders.append((out, surface))
            depths[i] = (out.depth_median * surface, v.K)
        reset = torch.zeros(self.params.num, dtype=torch.bool)
        for i, (out, surface) in enumerate(renders):
            v = views.at(i, factor)
            ys, xs = torch.nonzero(surface, as_tuple=True)
            if len(xs) == 0:
                continue
            best = best_source_ncc(out.depth_median, out.normal_cam, torch.stack([xs, ys], 1), v.K,
                                   torch.from_numpy(views.scene.K[i]).float(), views.grey_full[i],
                                   self._sources(i, depths), patch=lw.mv_patch,
                                   min_patch_std=lw.mv_min_patch_std, occlusion_rel_tol=pr.depth_rel_tol,
                                   ncc_gamma=lw.mv_ncc_gamma)
            marked = torch.zeros_like(surface)
            marked[ys, xs] = best < pr.ncc_min  # nan (no evidence) compares False
            reset |= visible_surfels_at(self.params.means, v.K, v.world_to_cam, out.depth_median, marked,
                                        pr.depth_rel_tol)
        if reset.any():
            cap = torch.logit(torch.tensor(pr.opacity, dtype=self.params.opacity_logits.dtype))
            ops.set_values(self.params, self.optimizer, "opacity_logits",
                           torch.where(reset, self.params.opacity_logits.clamp_max(cap), self.params.opacity_logits))
        return int(reset.sum())

    def _degenerate(self) -> torch.Tensor:
        """Surfels with non-finite parameters or gradients, or a degenerate scale. The
        common case costs one summation per tensor: rows are inspected only when a sum
        is not finite (NaN and Inf propagate through it)."""
        n = self.params.num
        bad = torch.zeros(n, dtype=torch.bool)
        for p in self.params.tensors().values():
            for t in (p.detach(), p.grad):
                if t is not None and not bool(torch.isfinite(t.sum())):
                    bad |= ~torch.isfinite(t.reshape(n, -1).sum(dim=1))
        ls = self.params.log_scales.detach()
        bad |= (ls.min(dim=1).values < math.log(MIN_SCALE)) | (ls.max(dim=1).values > math.log(MAX_SCALE * self.cfg.scene_extent))
        return bad

    def prune_outside(self) -> int:
        """Remove the surfels outside the region (after the last refinement they can still
        drift out); returns how many. A region that holds none of them keeps them all: a
        scene of zero surfels cannot be written."""
        if self.region is None:
            return 0
        outside = ~self.region.contains(self.params.means)
        n = int(outside.sum())
        if n == 0 or n == self.params.num:
            return 0
        ops.select(self.params, self.optimizer, ~outside)
        self.strategy.state.select(~outside)
        self.removed_outside += n
        return n

    def _remove(self, bad: torch.Tensor) -> None:
        keep = ~bad
        if not keep.any():
            raise NonFiniteLossError(f"every surfel became degenerate at iteration {self.it} (learning rates too high?)")
        ops.select(self.params, self.optimizer, keep)
        self.strategy.state.select(keep)
        self.removed_degenerate += int(bad.sum())


def masked_target(v: ViewData, background: float) -> torch.Tensor:
    """``(3, h, w)``: view ``v``'s image with the pixels outside its mask (if any) set to
    ``background``, what the render composited over that background is compared with."""
    if v.mask is None:
        return v.image
    m = v.mask.to(v.image.dtype)
    return v.image * m + background * (1.0 - m)


def _uncrop(x: torch.Tensor, window: tuple[int, int, int, int], size: tuple[int, int]) -> torch.Tensor:
    """A crop's ``(h, w)`` or ``(h, w, C)`` map placed at ``window`` ``(x0, y0, w, h)`` in a
    zero (False) map of the whole view's ``size`` ``(H, W)``; differentiable."""
    x0, y0, w, h = window
    H, W = size
    if x.dtype == torch.bool:
        whole = torch.zeros((H, W) + tuple(x.shape[2:]), dtype=torch.bool)
        whole[y0:y0 + h, x0:x0 + w] = x
        return whole
    pad = (x0, W - x0 - w, y0, H - y0 - h)
    if x.dim() == 3:
        return F.pad(x.permute(2, 0, 1), pad).permute(1, 2, 0)
    return F.pad(x, pad)


def train(params: SurfelParams, views: TrainViews, cfg: OptimizeConfig, loss: LossConfig,
          checkpoint: str | Path | None = None, backend: str | None = None,
          on_log: Callable[[dict], None] | None = None, log_every: int = 10,
          stop_after: int | None = None, progress: bool = False, log: Callable[[str], None] = print) -> TrainResult:
    """Train ``params`` in place; resume from ``checkpoint`` when it holds a state of this
    same configuration and input, and write it every ``cfg.checkpoint_every`` iterations.
    ``stop_after`` ends early after that many iterations (for tests of resuming)."""
    backend = resolve_backend(backend or cfg.backend)
    trainer = Trainer(params, views, cfg, loss, backend)
    ckpt = Path(checkpoint) if checkpoint else None
    resumed = trainer.it if (ckpt is not None and trainer.try_resume(ckpt, log)) else None
    spent_before = dict(trainer.spent)
    history: list[dict] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=cfg.iterations, initial=trainer.it, desc="optimize", unit="it", dynamic_ncols=True)
    last: dict = {}
    try:
        _loop(trainer, cfg, ckpt, history, last, on_log, log_every, stop_after, bar)
        if trainer.it >= cfg.iterations:
            trainer.prune_outside()
    except KeyboardInterrupt:
        saved = (trainer.it // cfg.checkpoint_every) * cfg.checkpoint_every if cfg.checkpoint_every else 0
        if ckpt is not None and saved > 0 and ckpt.is_file():
            raise Interrupted(f"interrupted at iteration {trainer.it}; the checkpoint {ckpt} (iteration {saved}) "
                              "resumes it: rerun the same command") from None
        raise Interrupted(f"interrupted at iteration {trainer.it}, before the first checkpoint "
                          f"(every {cfg.checkpoint_every} iterations); a rerun starts over") from None
    finally:
        if bar is not None:
            bar.close()
    return TrainResult(params=trainer.params, iterations=trainer.it, backend=backend, num_init=trainer.num_init,
                       history=history, seconds={k: trainer.seconds.get(k, 0.0) for k in TIMED},
                       removed_degenerate=trainer.removed_degenerate, removed_outside=trainer.removed_outside,
                       surfel_budget=trainer.budget.facts(), resumed_from=resumed, spent_before=spent_before,
                       final_terms={k: v for k, v in last.items() if k not in ("iteration", "view", "seconds")})


def _loop(trainer: Trainer, cfg: OptimizeConfig, ckpt: Path | None, history: list[dict], last: dict,
          on_log: Callable[[dict], None] | None, log_every: int, stop_after: int | None, bar) -> None:
    """The iterations of :func:`train`; ``history`` gets the logged rows and ``last`` the
    final row."""
    done = 0
    while trainer.it < cfg.iterations and (stop_after is None or done < stop_after):
        t0, c0 = time.perf_counter(), time.process_time()
        row = trainer.step()
        row["seconds"] = time.perf_counter() - t0
        last.clear()
        last.update(row)
        done += 1
        if row["iteration"] % log_every == 0 or trainer.it == cfg.iterations:
            history.append(row)
            if on_log:
                on_log(row)
        if bar is not None:
            bar.update(1)
            if row["iteration"] % log_every == 0:
                bar.set_postfix({k: f"{row[k]:.4g}" for k in ("total", "l1", "gcf", "nor", "dist") if k in row}
                                | {"N": row["surfels"]})
        trainer.spent["wall_s"] += time.perf_counter() - t0
        trainer.spent["cpu_s"] += time.process_time() - c0
        if ckpt is not None and cfg.checkpoint_every and trainer.it % cfg.checkpoint_every == 0:
            trainer.save_checkpoint(ckpt)
