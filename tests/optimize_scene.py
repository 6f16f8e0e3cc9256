"""A tiny training problem for the optimize tests: the analytic two-sphere scene of
``init_scene`` at a small size, an init cloud back-projected from its exact depth, and
priors (normals from the exact depth, default NCC features) written like the priors stage."""
from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np

from init_scene import make_scene
from pipeline import geometry
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.priors import PriorsConfig
from pipeline.init.io import PointCloud
from pipeline.priors import features as feat, normals as nrm
from pipeline.priors.io import FeaturePrior, NormalPrior, features_path, normals_path, write_features, write_normals


def tiny_problem(tmp: Path, width: int = 64, height: int = 48, stride: int = 3):
    """``(scene, cloud, priors_dir)``; the cloud holds every ``stride``-th GT pixel."""
    scene, depths = make_scene(width, height)
    pts, cols, nors = [], [], []
    priors = tmp / "priors"
    for i, (K, T, z) in enumerate(zip(scene.K, scene.world_to_cam, depths)):
        valid = z > 0
        depth = np.where(valid, z, 0.0)
        n_cam, ok = nrm.normals_from_depth(depth, valid, K, PriorsConfig.default(normal_step_px=1, normal_smooth_sigma_px=0.0,
                                                                         normal_max_slant_deg=85.0), where="test")
        write_normals(normals_path(priors, scene.view_ids[i]), NormalPrior(scene.view_ids[i], n_cam, ok, "default"))
        f = feat.default_features(scene.images[i], patch=3, scales=(1,), min_contrast=0.002, where="test")
        write_features(features_path(priors, scene.view_ids[i]),
                       FeaturePrior(scene.view_ids[i], f, feat.feature_image_size(height, width), "default"), "float32")
        world = geometry.backproject_depth(K, T, depth)
        sel = valid & ok
        sel[::stride, :] &= True
        keep = np.zeros_like(sel)
        keep[::stride, ::stride] = True
        sel &= keep
        pts.append(world[sel])
        cols.append(scene.images[i][sel])
        nors.append(n_cam[sel] @ T[:3, :3])  # camera -> world: R^T n, as rows
    cloud = PointCloud(np.concatenate(pts), np.concatenate(cols).astype(np.float64), np.concatenate(nors),
                       np.ones(sum(len(p) for p in pts)))
    return scene, cloud, priors


# The tiny run's settings over conf/'s defaults: its short schedule, and where conf/'s default
# preset has others, the settings these tests were written with (the dataclass defaults before
# conf/ became the one source of each, issue 60): full resolution, every init point, L_gcf and
# L_nor on, L_mv, L_smooth and the photo reset off, the means' rate decayed 100x, a fixed
# surfel budget (a budget per object pixel would give the tiny views' few hundred).
TINY_OPTIMIZE = {
    "preset": "custom", "iterations": 12, "sh_degree": 1, "sh_every": 5, "checkpoint_every": 0,
    "init_voxel_norm": 0.0, "downscale": [[0.0, 1]], "gcf_max_points": 16384, "mv_textured_points": False,
    "lr": {"means_final": 1.6e-6},
    "densify": {"start_iter": 3, "stop_iter": 10, "every": 3, "reset_every": 8, "grad_threshold": 1e-6, "max_surfels": 5000,
                "surfels_per_object_px": 0.0},
    "start": {"gcf": 0, "nor": 0, "d": 2, "dn": 2, "mv": 7000},
    "photo_reset": {"enabled": False},
}
TINY_LOSS = {"lambda_gcf": 2.0, "lambda_nor": 0.25, "lambda_mv": 0.0, "lambda_mvgeo": 0.0, "mv_max_cost": 2.0,
             "mv_ncc_gamma": 0.0, "lambda_smooth": 0.0, "smooth_max_std": 0.0}


def tiny_config(**over) -> tuple[OptimizeConfig, LossConfig]:
    """The tiny run's optimize and loss configs with ``over`` (fields of either; a mapping for
    a nested section merges over the tiny run's)."""
    def changed(cls, base):
        names = {f.name for f in fields(cls)}
        mine = {k: v for k, v in over.items() if k in names}
        return {**base, **mine, **{k: {**base[k], **v} for k, v in mine.items() if isinstance(v, dict) and k in base}}

    return OptimizeConfig.default(**changed(OptimizeConfig, TINY_OPTIMIZE)), LossConfig.default(**changed(LossConfig, TINY_LOSS))


def write_stage_inputs(root: Path) -> tuple[Path, Path]:
    """The tiny problem written to disk as the optimize command reads it: ``root/scene`` (DTU
    layout), ``root/init/points.ply``, the priors, and ``root/params.yaml`` for a 10-iteration
    run (checkpoints every 4). Returns ``(root, priors_dir)``."""
    import yaml

    from pipeline.config.params import load_params
    from pipeline.data import dtu
    from pipeline.init.io import write_ply

    scene, cloud, priors = tiny_problem(root)
    ids = scene.view_ids
    dtu.write_scene(root / "scene", images=dict(zip(ids, scene.images)), K=dict(zip(ids, scene.K)),
                    world_to_cam=dict(zip(ids, scene.world_to_cam)), norm_to_world=scene.norm_to_world,
                    masks=dict(zip(ids, scene.masks)), meta={"name": "tiny"})
    write_ply(root / "init" / "points.ply", cloud)
    params = load_params(Path(__file__).resolve().parents[1] / "params.yaml")
    params["optimize"].update(iterations=10, checkpoint_every=4, init_voxel_norm=0.0, downscale=[[0.0, 1]],
                              start={"gcf": 0, "nor": 0, "d": 3, "dn": 6, "mv": 7000})
    params["optimize"]["densify"].update(start_iter=3, stop_iter=8, every=3)
    params["mesh"]["init_depth_rel_tol"] = 0.0  # a cloud without depth maps: nothing for the mesh to merge
    (root / "params.yaml").write_text(yaml.safe_dump(params))
    return root, priors


def interrupt_training_at(monkeypatch, iteration: int):
    """Make training raise KeyboardInterrupt (Ctrl-C) when it reaches ``iteration``; returns
    a function that undoes it (for the rerun that resumes)."""
    from pipeline.optimize.train import Trainer

    step = Trainer.step

    def interrupted(self):
        if self.it == iteration:
            raise KeyboardInterrupt
        return step(self)

    monkeypatch.setattr(Trainer, "step", interrupted)
    return lambda: monkeypatch.setattr(Trainer, "step", step)
