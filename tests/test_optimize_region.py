"""Surfels only where the object is (issue 58): the region (sphere and the masks' visual hull)
and the scene's surfel budget against slow per-point references; densification that never
grows outside and prunes what lies there; a training whose init cloud holds floaters in the
background ends with every surfel inside."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from optimize_scene import tiny_config, tiny_problem
from pipeline.config.optimize import DensifyConfig
from pipeline.init.io import PointCloud
from pipeline.optimize import init_from_cloud, make_views, train
from pipeline.optimize import ops
from pipeline.optimize.region import SurfelRegion, region_from_views, sphere_silhouette, surfel_budget
from pipeline.optimize.seed import init_params
from pipeline.optimize.strategy import DensifyStrategy


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    return tiny_problem(tmp_path_factory.mktemp("tiny_region"))


def _reference_contains(points, K, w2c, masks, radius, tol_px):
    """One point and one view at a time: the homogeneous projection ``K [R | t] X``, the
    pixel it rounds to, and a brute-force distance from that pixel to the nearest mask pixel."""
    out = []
    for p in np.asarray(points, np.float64):
        ok = math.sqrt(float(p @ p)) <= radius
        for k, T, m in zip(K, w2c, masks):
            if not ok:
                break
            x = k @ (T[:3] @ np.append(p, 1.0))
            if x[2] <= 1e-9:
                continue
            u, v = int(np.rint(x[0] / x[2])), int(np.rint(x[1] / x[2]))
            if not (0 <= u < m.shape[1] and 0 <= v < m.shape[0]):
                continue
            ys, xs = np.nonzero(m)
            ok = len(xs) > 0 and float(np.min((xs - u) ** 2 + (ys - v) ** 2)) <= tol_px ** 2
        out.append(ok)
    return np.array(out)


def _points_around(scene, n, rng):
    """Points spread over the unit sphere's neighbourhood (some outside it, some behind or
    beside the cameras' images), half near the object's surface so both answers occur."""
    return np.concatenate([rng.uniform(-1.3, 1.3, size=(n // 2, 3)), rng.normal(scale=0.25, size=(n - n // 2, 3))])


@pytest.mark.parametrize("tol_px", [0.0, 1.5, 4.0])
def test_region_contains_matches_the_per_point_reference(problem, tol_px):
    scene, _, _ = problem
    cfg, loss = tiny_config()
    cfg = replace(cfg, region=replace(cfg.region, enabled=True, hull_tolerance_px=tol_px))
    views = make_views(scene, None, cfg, replace(loss, lambda_nor=0.0, lambda_gcf=0.0))
    masks = views.training_masks()
    assert masks is not None
    region = region_from_views(scene, masks, cfg)
    pts = _points_around(scene, 400, np.random.default_rng(0))
    got = region.contains(torch.from_numpy(pts)).numpy()
    ref = _reference_contains(pts, scene.K, scene.world_to_cam_normalised(), masks, cfg.region.sphere_radius, tol_px)
    assert got.dtype == bool and got.shape == (400,)
    assert (got == ref).all(), np.flatnonzero(got != ref)
    assert 0 < got.sum() < len(got)  # both answers occur
    # Without masks: the sphere alone.
    bare = region_from_views(scene, None, cfg)
    assert (bare.contains(pts).numpy() == (np.linalg.norm(pts, axis=1) <= cfg.region.sphere_radius)).all()
    assert region_from_views(scene, masks, replace(cfg, region=replace(cfg.region, enabled=False))) is None


def test_sphere_silhouette_matches_the_closest_approach_of_each_ray(problem):
    scene, _, _ = problem
    w2c = scene.world_to_cam_normalised()
    for radius in (0.3, 1.0):
        for i in range(scene.num_views):
            got = sphere_silhouette(scene.K[i], w2c[i], (scene.height, scene.width), radius)
            R, t = w2c[i][:3, :3], w2c[i][:3, 3]
            centre = -R.T @ t  # camera centre, normalised frame
            ref = np.zeros_like(got)
            for v in range(scene.height):
                for u in range(scene.width):
                    d = R.T @ np.linalg.solve(scene.K[i], [u, v, 1.0])
                    d /= np.linalg.norm(d)
                    s = -float(centre @ d)  # ray parameter of the point nearest the origin
                    ref[v, u] = s > 0 and float(np.linalg.norm(centre + s * d)) <= radius
            assert (got == ref).all()
    inside = np.eye(4)
    inside[2, 3] = 0.5  # a camera inside the sphere sees it everywhere
    assert sphere_silhouette(scene.K[0], inside, (scene.height, scene.width), 1.0).all()


def test_budget_follows_the_object_area_up_to_the_ceiling(problem):
    scene, _, _ = problem
    cfg, _ = tiny_config()
    masks = [np.asarray(m, bool) for m in scene.masks]
    area = np.mean([m.sum() for m in masks])
    per_px = lambda p, ceiling: replace(cfg, densify=replace(cfg.densify, surfels_per_object_px=p, max_surfels=ceiling))
    b = surfel_budget(scene, masks, per_px(0.5, 10 ** 6))
    assert b.surfels == math.ceil(0.5 * area) and b.source == "masks" and b.facts()["object_px_mean"] == round(area, 1)
    assert surfel_budget(scene, masks, per_px(0.5, 100)).surfels == 100  # the ceiling wins
    assert surfel_budget(scene, masks, per_px(0.0, 777)).surfels == 777  # 0: the ceiling for every scene
    w2c = scene.world_to_cam_normalised()
    sphere = np.mean([sphere_silhouette(scene.K[i], w2c[i], (scene.height, scene.width), cfg.region.sphere_radius).sum()
                      for i in range(scene.num_views)])
    bare = surfel_budget(scene, None, per_px(0.5, 10 ** 6))
    assert bare.source == "sphere" and bare.surfels == math.ceil(0.5 * sphere) and sphere >= area


class _HalfSpace(SurfelRegion):
    """A region whose inside is x < 0, to steer the strategy by hand."""

    def __init__(self):
        super().__init__(sphere_radius=10.0, K=np.zeros((0, 3, 3)), world_to_cam=np.zeros((0, 4, 4)), hull=None)

    def contains(self, means):
        return torch.as_tensor(means).detach()[:, 0] < 0


def test_densification_never_grows_outside_and_prunes_what_lies_there():
    rng = np.random.default_rng(0)
    pts = np.array([[-0.5, 0, 0], [-0.4, 0.1, 0], [0.5, 0, 0], [0.4, 0.1, 0], [-0.02, 0, 0], [0.3, 0.3, 0]])
    params = init_params(pts, None, rng.random((6, 3)), 0, 0.9, rng, dtype=torch.float64)
    with torch.no_grad():
        params.log_scales[:] = math.log(0.001)  # small: cloned
        params.log_scales[4] = math.log(0.2)  # large, at the border: its children land on both sides
    opt = ops.make_optimizer(params, {k: 0.01 for k in params.tensors()}, (0.9, 0.999))
    st = DensifyStrategy(DensifyConfig.default(start_iter=0, stop_iter=100, every=10, grad_threshold=1e-3, reset_every=0,
                                               max_surfels=100, prune_opacity=0.0), region=_HalfSpace())
    st.initialize(params.num)
    st.step_post_backward(params, torch.full((6, 2), 1.0), torch.full((6,), 3, dtype=torch.int32), 400, 300)
    done = st.step_post_update(params, opt, 10, torch.Generator().manual_seed(1))
    # Only the three inside were refined (two clones, one split); the three outside were pruned.
    assert done["cloned"] == 2 and done["split"] == 1
    assert done["outside"] >= 3
    assert bool(st.region.contains(params.means).all())
    assert params.num == 6 + 2 + 1 - done["outside"]


def test_training_with_background_floaters_ends_inside_the_region(problem):
    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=12, surface_alpha=0.05)
    cfg = replace(cfg, region=replace(cfg.region, enabled=True), densify=replace(cfg.densify, reset_every=0))
    views = make_views(scene, priors, cfg, loss)
    masks = views.training_masks()
    region = region_from_views(scene, masks, cfg)
    # Floaters: points in front of the first camera that it sees outside its mask.
    w2c = scene.world_to_cam_normalised()[0]
    rng = np.random.default_rng(3)
    cam = np.column_stack([rng.uniform(-0.3, 0.3, 200), rng.uniform(-0.2, 0.2, 200), np.full(200, 2.0)])
    floaters_norm = (cam - w2c[:3, 3]) @ w2c[:3, :3]
    floaters_norm = floaters_norm[~region.contains(floaters_norm).numpy()]
    assert len(floaters_norm) > 20
    S = scene.norm_to_world
    floaters_mm = floaters_norm @ S[:3, :3].T + S[:3, 3]
    dirty = PointCloud(np.concatenate([cloud.points_mm, floaters_mm]),
                       np.concatenate([cloud.colors, np.full((len(floaters_mm), 3), 0.5)]),
                       np.concatenate([cloud.normals, np.tile([0.0, 0.0, 1.0], (len(floaters_mm), 1))]),
                       np.ones(len(cloud.points_mm) + len(floaters_mm)))
    clean = init_from_cloud(cloud, scene, cfg, region=region)
    seeded = init_from_cloud(dirty, scene, cfg, region=region)
    assert seeded.num == clean.num  # every floater dropped before training
    # Floaters put straight into the surfels (a caller without init_from_cloud's region):
    # the refinements and the final prune remove them.
    free = init_from_cloud(dirty, scene, cfg)
    assert not bool(region.contains(free.means).all())
    result = train(free, views, cfg, loss, log_every=1)
    assert bool(region.contains(result.params.means).all())
    assert result.removed_outside >= len(floaters_norm)
    assert result.surfel_budget["surfels"] == surfel_budget(scene, masks, cfg).surfels
