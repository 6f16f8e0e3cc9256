"""Training on the cuda backend (gsplat): skipped without CUDA and gsplat."""
from __future__ import annotations

import importlib.util
from dataclasses import replace

import numpy as np
import pytest
import torch

from optimize_scene import tiny_config, tiny_problem
from pipeline.optimize import init_from_cloud, make_views, train

pytestmark = [
    pytest.mark.cuda,
    pytest.mark.skipif(
        not torch.cuda.is_available() or importlib.util.find_spec("gsplat") is None, reason="needs CUDA and gsplat"
    ),
]


def test_training_on_the_cuda_backend_lowers_the_photometric_error(tmp_path):
    scene, cloud, priors = tiny_problem(tmp_path)
    cfg, loss = tiny_config(iterations=24, surface_alpha=0.05, backend="cuda")
    cfg = replace(cfg, densify=replace(cfg.densify, reset_every=0))  # a reset darkens every render
    params = init_from_cloud(cloud, scene, cfg)
    res = train(params, make_views(scene, priors, cfg, loss), cfg, loss, log_every=1)
    assert res.backend == "cuda"
    for name, t in res.params.tensors().items():
        assert torch.isfinite(t).all(), name
    first = np.mean([r["l1"] for r in res.history[:3]])
    last = np.mean([r["l1"] for r in res.history[-3:]])
    assert last < first
