"""GCGS optimisation: 2D Gaussian surfels seeded from the init cloud and trained on the
input views with the photometric, feature (L_gcf), normal-prior (L_nor), distortion and
depth-normal losses (docs/optimize.md); the loss terms live in :mod:`pipeline.losses`.

* :mod:`seed`: surfels seeded from a cloud (the model and its PLY files: :mod:`pipeline.surfels`).
* :mod:`strategy` / :mod:`ops`: densification with explicit state; optimizer-consistent edits.
* :mod:`views`: training views and priors at each resolution of the schedule.
* :mod:`start`: the starting state: surfels from the init cloud, the training views.
* :mod:`train`: the loop, checkpoints, non-finite guards.
"""
from __future__ import annotations

from pipeline.optimize.start import (
    MIN_INIT_POINTS,
    MIN_SURFELS,
    budget_downsample,
    init_from_cloud,
    make_views,
    uses_masks,
)
from pipeline.optimize.train import NonFiniteLossError, TrainResult, train
from pipeline.surfels import SurfelInitError

__all__ = ["MIN_INIT_POINTS", "MIN_SURFELS", "NonFiniteLossError", "SurfelInitError", "TrainResult", "budget_downsample",
           "init_from_cloud", "make_views", "train", "uses_masks"]
