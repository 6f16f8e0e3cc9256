"""Figures of a point cloud (world mm) against a scene's ground truth.

For a cloud C and the GT (:class:`~pipeline.evaluation.gt.GroundTruth`):

* ``median_to_surface_mm`` / ``p90_to_surface_mm``: distances from C's points to the GT
  mesh surface (the GT points when the GT folder has no ``mesh.ply``).
* ``accuracy_mm`` / ``completeness_mm`` / ``overall_mm``: the DTU-script means with the
  cloud as the data points (no mesh sampling, no mask culling): C in the observation mask
  -> GT points, and GT points above the ground plane -> C in the bounding box, each over
  distances below ``evaluate.max_dist_mm`` (None when no distance is below it).
* ``precision_1mm`` / ``recall_1mm``: fraction of C within 1 mm of the GT surface, and of
  the GT points above the plane within 1 mm of C.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pipeline.config.evaluate import EvaluateConfig
from pipeline.evaluation.gt import GroundTruth, read_mesh
from pipeline.raycast import distance_to_mesh


def cloud_metrics(points_mm: np.ndarray, ground: GroundTruth, cfg: EvaluateConfig) -> dict:
    """The module docstring's figures of a (N, 3) cloud in world mm."""
    mesh_path = ground.root / "mesh.ply"
    if mesh_path.is_file():
        d_surf = distance_to_mesh(points_mm, *read_mesh(mesh_path))
        surface = "GT mesh"
    else:
        d_surf, _ = cKDTree(ground.points_mm).query(points_mm)
        surface = "GT points"
    inbound, in_obs = ground.box_and_observed(points_mm, cfg.patch_mm)
    data_in = points_mm[inbound]
    d_acc, _ = cKDTree(ground.points_mm).query(data_in[in_obs], distance_upper_bound=cfg.max_dist_mm)
    gt_above = ground.points_mm[ground.above_plane(ground.points_mm)]
    if len(data_in):
        d_comp, _ = cKDTree(data_in).query(gt_above, distance_upper_bound=cfg.max_dist_mm)
    else:
        d_comp = np.full(len(gt_above), np.inf)

    def mean_below(d: np.ndarray) -> float | None:
        d = d[d < cfg.max_dist_mm]
        return float(d.mean()) if len(d) else None

    acc, comp = mean_below(d_acc), mean_below(d_comp)
    return {
        "points": int(len(points_mm)),
        "median_to_surface_mm": float(np.median(d_surf)),
        "p90_to_surface_mm": float(np.percentile(d_surf, 90)),
        "surface": surface,
        "accuracy_mm": acc,
        "completeness_mm": comp,
        "overall_mm": (acc + comp) / 2 if acc is not None and comp is not None else None,
        "precision_1mm": float(np.mean(d_surf < 1.0)),
        "recall_1mm": float(np.mean(d_comp < 1.0)),
    }
