"""GCGS optimisation: 2D Gaussian surfels seeded from the init cloud and trained on the
input views with the photometric, feature (L_gcf), normal-prior (L_nor), distortion and
depth-normal losses (docs/optimize.md).

* :mod:`surfels`: parameters, initialisation, 2DGS-layout PLY I/O.
* :mod:`strategy` / :mod:`ops`: densification with explicit state; optimizer-consistent edits.
* :mod:`views`: training views and priors at each resolution of the schedule.
* :mod:`terms`: D-SSIM, depth-normal consistency, mask term.
* :mod:`train`: the loop, checkpoints, non-finite guards.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.config import ConfigError, LossConfig, OptimizeConfig
from pipeline.data.scene import Scene
from pipeline.init.fusion import voxel_downsample
from pipeline.init.io import PointCloud
from pipeline.optimize.surfels import SurfelInitError, SurfelParams, init_params
from pipeline.optimize.train import NonFiniteLossError, TrainResult, train
from pipeline.optimize.views import TrainViews

__all__ = ["NonFiniteLossError", "SurfelInitError", "TrainResult", "init_from_cloud", "make_views", "train",
           "uses_masks"]


def uses_masks(scene: Scene, cfg: OptimizeConfig) -> bool:
    """Masks are used when ``optimize.masks`` is on, or auto and the scene has them."""
    if cfg.masks == "on" and scene.masks is None:
        raise ConfigError(f"{scene.source}: optimize.masks is on but the scene has no masks")
    return cfg.masks == "on" or (cfg.masks == "auto" and scene.masks is not None)


def init_from_cloud(cloud: PointCloud, scene: Scene, cfg: OptimizeConfig, where: str = "init cloud") -> SurfelParams:
    """Surfels from an init cloud (world mm -> the normalised frame of ``scene``)."""
    S = scene.norm_to_world
    pts = (np.asarray(cloud.points_mm, np.float64) - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    normals, colors = cloud.normals.astype(np.float64), cloud.colors.astype(np.float64)
    if cfg.init_voxel_norm > 0 and len(pts):
        pts, normals, colors = voxel_downsample(pts, cfg.init_voxel_norm, normals, colors)
        norm = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = np.where(norm > 1e-9, normals / np.maximum(norm, 1e-12), [0.0, 0.0, 1.0])
    rng = np.random.default_rng(cfg.seed)
    return init_params(pts, normals if cfg.init_normals else None, colors, cfg.sh_degree, cfg.init_opacity, rng,
                       where=where)


def make_views(scene: Scene, priors_dir: str | Path | None, cfg: OptimizeConfig, loss: LossConfig) -> TrainViews:
    return TrainViews(scene, priors_dir, use_masks=uses_masks(scene, cfg), want_normals=loss.lambda_nor > 0,
                      want_features=loss.lambda_gcf > 0, near=cfg.near, far=cfg.far)
