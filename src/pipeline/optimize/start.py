"""The trainer's starting state, built from the stage's files: the initial surfels from
the init cloud (averaged down to the surfel budget) and the training views with the
priors the loss weights ask for.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.data.scene import Scene
from pipeline.errors import ConfigError, DegenerateResultError
from pipeline.geometry import voxel_downsample
from pipeline.init.io import PointCloud
from pipeline.optimize.region import SurfelRegion
from pipeline.optimize.seed import init_params
from pipeline.optimize.views import TrainViews
from pipeline.surfels import SurfelParams

# Fewer points than MIN_INIT_POINTS seed no surface (a sparse SfM cloud of a few dozen
# still does: densification grows it); a training that ends with fewer than MIN_SURFELS
# surfels made no surface and writes nothing.
MIN_INIT_POINTS = 8
MIN_SURFELS = 32


def uses_masks(scene: Scene, cfg: OptimizeConfig) -> bool:
    """Masks are used when ``optimize.masks`` is on, or auto and the scene has them."""
    if cfg.masks == "on" and scene.masks is None:
        raise ConfigError(f"{scene.source}: optimize.masks is on but the scene has no masks")
    return cfg.masks == "on" or (cfg.masks == "auto" and scene.masks is not None)


def init_from_cloud(cloud: PointCloud, scene: Scene, cfg: OptimizeConfig, where: str = "init cloud",
                    region: SurfelRegion | None = None, max_surfels: int | None = None) -> SurfelParams:
    """Surfels from an init cloud (world mm -> the normalised frame of ``scene``).

    Points outside ``region`` (None: anywhere) are dropped. The rest is averaged in voxels
    of ``cfg.init_voxel_norm``, coarser ones while it holds more points than the surfel
    budget ``max_surfels`` (None: ``cfg.densify.max_surfels``), so a budget caps the whole
    run and not only densification, and the kept points still cover the object."""
    S = scene.norm_to_world
    pts = (np.asarray(cloud.points_mm, np.float64) - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    normals, colors = cloud.normals.astype(np.float64), cloud.colors.astype(np.float64)
    n_cloud = len(pts)
    if region is not None and n_cloud:
        keep = region.contains(pts).numpy()
        pts, normals, colors = pts[keep], normals[keep], colors[keep]
        if not len(pts):
            raise DegenerateResultError(f"{where}: none of its {n_cloud} init points lies inside the region "
                                        f"(optimize.region: the sphere of radius {region.sphere_radius} and the masks' "
                                        f"visual hull); is the cloud in this scene's frame?")
    budget = cfg.densify.max_surfels if max_surfels is None else max_surfels
    pts, normals, colors = budget_downsample(pts, normals, colors, cfg.init_voxel_norm, budget)
    if 0 < len(pts) < MIN_INIT_POINTS:
        raise DegenerateResultError(f"{where}: {n_cloud} init point(s) give {len(pts)} surfels, fewer than "
                                    f"{MIN_INIT_POINTS}: too few to seed a surface (did the init stage match anything?)")
    rng = np.random.default_rng(cfg.seed)
    return init_params(pts, normals if cfg.init_normals else None, colors, cfg.sh_degree, cfg.init_opacity, rng,
                       where=where)


def make_views(scene: Scene, priors_dir: str | Path | None, cfg: OptimizeConfig, loss: LossConfig,
               mvs_depth_dir: str | Path | None = None) -> TrainViews:
    """The training views; ``mvs_depth_dir`` (the init's ``depth/``) is read when L_mvs is on."""
    return TrainViews(scene, priors_dir, use_masks=uses_masks(scene, cfg), want_normals=loss.lambda_nor > 0,
                      want_features=loss.lambda_gcf > 0, near=cfg.near, far=cfg.far,
                      mvs_depth_dir=mvs_depth_dir if loss.lambda_mvs > 0 else None)


def budget_downsample(pts: np.ndarray, normals: np.ndarray, colors: np.ndarray, voxel: float,
                      max_points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Average ``(N, 3)`` points with their normals and colours in voxels of ``voxel``
    (0: none), then in voxels grown by sqrt(count / ``max_points``) (points on a surface:
    their count falls with the voxel's area) until at most ``max_points`` remain."""
    if max_points < 1:
        raise ConfigError(f"optimize.densify.max_surfels must be >= 1, got {max_points}")
    if (voxel <= 0 and len(pts) <= max_points) or not len(pts):
        return pts, normals, colors
    out = voxel_downsample(pts, voxel, normals, colors) if voxel > 0 else (pts, normals, colors)
    if len(out[0]) > max_points:
        # Start from the spacing that max_points would have on the bounding box's largest face.
        ext = np.sort(np.ptp(pts, axis=0))
        size = max(voxel, float(np.sqrt(ext[1] * ext[2] / max_points)), 1e-12)
        while len(out[0]) > max_points:
            out = voxel_downsample(pts, size, normals, colors)
            size *= max(1.05, float(np.sqrt(len(out[0]) / max_points)))
    p, n, c = out
    norm = np.linalg.norm(n, axis=1, keepdims=True)  # averaged normals: unit again, a default where they cancel
    return p, np.where(norm > 1e-9, n / np.maximum(norm, 1e-12), [0.0, 0.0, 1.0]), c
