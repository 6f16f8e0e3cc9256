"""The training loop on a tiny analytic scene: every term on, resume bitwise equal, the
non-finite guard, and the extremes the issue lists (1 and 0 init points, black images,
invalid priors, zero features, exploding learning rates, a scene 1000x larger or smaller)."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from optimize_scene import tiny_config, tiny_problem
from pipeline import geometry
from pipeline.errors import ConfigError, DegenerateResultError
from pipeline.init.io import PointCloud
from pipeline.optimize import NonFiniteLossError, SurfelInitError, budget_downsample, init_from_cloud, make_views, train
from pipeline.optimize.seed import init_params
from pipeline.optimize.train import Trainer
from pipeline.priors.io import FeaturePrior, NormalPrior, features_path, normals_path, read_features, read_normals, write_features, write_normals
from pipeline.runs.optimize import timing_report


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    return tiny_problem(tmp_path_factory.mktemp("tiny"))


def _run(scene, cloud, priors, cfg, loss, **kw):
    params = init_from_cloud(cloud, scene, cfg)
    views = make_views(scene, priors, cfg, loss)
    return train(params, views, cfg, loss, log_every=1, **kw)


def _finite(result):
    for name, t in result.params.tensors().items():
        assert torch.isfinite(t).all(), name
    for row in result.history:
        for k, v in row.items():
            assert np.isfinite(v), (k, row)


def test_all_terms_run_and_photometric_error_falls(problem):
    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=24, surface_alpha=0.05)
    cfg = replace(cfg, densify=replace(cfg.densify, reset_every=0))  # a reset darkens every render
    res = _run(scene, cloud, priors, cfg, loss)
    _finite(res)
    seen = set().union(*(r.keys() for r in res.history))
    assert {"photo", "gcf", "nor", "dn", "dist", "mask"} <= seen
    assert any(r.get("gcf", 0) > 0 for r in res.history) and any(r.get("nor", 0) > 0 for r in res.history)
    first = np.mean([r["l1"] for r in res.history[:3]])
    last = np.mean([r["l1"] for r in res.history[-3:]])
    assert last < first
    assert res.params.num != res.num_init  # densification acted


def test_resume_is_bitwise_equal(problem, tmp_path):
    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=12, checkpoint_every=4, surface_alpha=0.05)
    straight = _run(scene, cloud, priors, cfg, loss)
    ckpt = tmp_path / "ckpt.pt"
    part = _run(scene, cloud, priors, cfg, loss, checkpoint=ckpt, stop_after=6)
    assert part.iterations == 6 and ckpt.is_file()
    resumed = _run(scene, cloud, priors, cfg, loss, checkpoint=ckpt)
    assert resumed.resumed_from == 4 and resumed.iterations == 12
    # The time of the first run (up to its checkpoint) is carried into the resumed run's report.
    assert straight.spent_before == {"wall_s": 0.0, "cpu_s": 0.0}
    assert resumed.spent_before["wall_s"] > 0 and resumed.spent_before["cpu_s"] > 0
    usage = {"wall_s": 1.0, "cpu_s": 2.0, "peak_rss_mb": 3.0}
    report = timing_report(resumed, usage, "tiny")
    assert report["wall_s"] == round(1.0 + resumed.spent_before["wall_s"], 2)
    assert report["cpu_s"] == round(2.0 + resumed.spent_before["cpu_s"], 2)
    assert (report["wall_s_this_run"], report["iterations_this_run"]) == (1.0, 8)
    assert report["s_per_iteration"] == round(sum(resumed.seconds.values()) / 12, 4)
    for k, a in straight.params.tensors().items():
        assert torch.equal(a, resumed.params.tensors()[k]), k
    # A checkpoint of another configuration is ignored, not loaded.
    other, _ = tiny_config(iterations=12, checkpoint_every=4, seed=1)
    res = _run(scene, cloud, priors, other, loss, checkpoint=ckpt, stop_after=1)
    assert res.resumed_from is None


def test_non_finite_loss_names_the_term_and_iteration(problem):
    scene, cloud, priors = problem
    bad = replace(scene, images=scene.images.copy())
    bad.images[0, 10, 10, 0] = np.nan
    cfg, loss = tiny_config(iterations=3)
    with pytest.raises(NonFiniteLossError, match=r"loss term photo is nan at iteration \d"):
        _run(bad, cloud, priors, cfg, loss)


def test_init_cloud_of_zero_and_one_point(problem):
    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=4)
    empty = PointCloud(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))
    with pytest.raises(SurfelInitError, match="no point"):
        init_from_cloud(empty, scene, cfg)
    one = PointCloud(cloud.points_mm[:1], cloud.colors[:1], cloud.normals[:1], cloud.confidence[:1])
    with pytest.raises(DegenerateResultError, match="too few to seed a surface"):
        init_from_cloud(one, scene, cfg)
    # The trainer's numerics still hold for a single surfel (densification may grow it).
    S = scene.norm_to_world
    p = (cloud.points_mm[:1] - S[:3, 3]) @ np.linalg.inv(S[:3, :3]).T
    params = init_params(p, cloud.normals[:1], cloud.colors[:1], cfg.sh_degree, cfg.init_opacity,
                         np.random.default_rng(0))
    _finite(train(params, make_views(scene, priors, cfg, loss), cfg, loss, log_every=1))


def test_budget_caps_the_init_cloud_and_keeps_its_extent():
    """A budget below the init cloud's size thins the cloud (not only densification), spread
    over the whole surface: a 200x200 grid on a 1x1 square kept within 1000 points."""
    g = np.linspace(0.0, 1.0, 200)
    x, y = np.meshgrid(g, g)
    pts = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    normals = np.tile([0.0, 0.0, 2.0], (len(pts), 1))  # not unit: averaged ones are renormalised
    colors = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    p, n, c = budget_downsample(pts, normals, colors, 0.0, 1000)
    assert 500 <= len(p) <= 1000
    assert np.ptp(p[:, 0]) > 0.9 and np.ptp(p[:, 1]) > 0.9  # still covers the square
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)
    # Each kept point is the mean of its voxel: its colour equals its position.
    np.testing.assert_allclose(c[:, :2], p[:, :2], atol=1e-12)
    same = budget_downsample(pts, normals, colors, 0.0, len(pts))  # at the budget: untouched
    assert same[0] is pts and same[1] is normals
    with pytest.raises(ConfigError, match="max_surfels"):
        budget_downsample(pts, normals, colors, 0.0, 0)


def test_init_from_cloud_respects_the_surfel_budget(problem):
    scene, cloud, _ = problem
    cfg, _ = tiny_config()
    free = init_from_cloud(cloud, scene, cfg)
    budget = free.num // 3
    capped = init_from_cloud(cloud, scene, replace(cfg, densify=replace(cfg.densify, max_surfels=budget)))
    assert 0 < capped.num <= budget < free.num


def test_black_images_invalid_priors_and_zero_features(problem, tmp_path):
    scene, cloud, priors = problem
    black = replace(scene, images=np.zeros_like(scene.images))
    bad_priors = tmp_path / "priors"
    for v in scene.view_ids:
        n = read_normals(normals_path(priors, v))
        write_normals(normals_path(bad_priors, v), NormalPrior(v, n.normal_cam, np.zeros_like(n.valid), n.backend))
        f = read_features(features_path(priors, v))
        write_features(features_path(bad_priors, v), FeaturePrior(v, np.zeros_like(f.features), f.image_size, f.backend),
                       "float32")
    cfg, loss = tiny_config(iterations=8, surface_alpha=0.0)
    res = _run(black, cloud, bad_priors, cfg, loss)
    _finite(res)
    assert all(r.get("nor", 0.0) == 0.0 for r in res.history)  # no valid prior pixel: the term is 0


def test_exploding_learning_rates_remove_degenerate_surfels(problem):
    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=6)
    fast = replace(cfg, lr=replace(cfg.lr, log_scales=4.0, means=1.0, means_final=1.0))
    res = _run(scene, cloud, priors, fast, loss)
    _finite(res)
    assert res.removed_degenerate > 0 and res.params.num > 0
    s = torch.exp(res.params.log_scales.detach())
    assert torch.all((s > 1e-8) & (s < 10.0))
    # So high that every surfel degenerates in one step: a clear error, not a NaN model.
    wild = replace(cfg, lr=replace(cfg.lr, log_scales=1e3))
    with pytest.raises(NonFiniteLossError, match="every surfel became degenerate at iteration 0"):
        _run(scene, cloud, priors, wild, loss)


def test_adam_takes_the_configured_betas_and_they_change_the_run(problem, tmp_path):
    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=8, checkpoint_every=4)
    slow = replace(cfg, adam_betas=[0.98, 0.9998])
    trainer = Trainer(init_from_cloud(cloud, scene, slow), make_views(scene, priors, slow, loss), slow, loss)
    assert {tuple(g["betas"]) for g in trainer.optimizer.param_groups} == {(0.98, 0.9998)}
    a, b = _run(scene, cloud, priors, cfg, loss), _run(scene, cloud, priors, slow, loss)
    assert not torch.equal(a.params.means, b.params.means)
    # A resumed run keeps them (the optimizer is rebuilt from the config, then its state loaded).
    ckpt = tmp_path / "ckpt.pt"
    _run(scene, cloud, priors, slow, loss, checkpoint=ckpt, stop_after=5)
    resumed = _run(scene, cloud, priors, slow, loss, checkpoint=ckpt)
    assert resumed.resumed_from == 4 and torch.equal(resumed.params.means, b.params.means)


@pytest.mark.parametrize("factor", [1000.0, 0.001])
def test_scene_scale_does_not_change_the_normalised_result(problem, factor):
    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=6, surface_alpha=0.05)
    base = _run(scene, cloud, priors, cfg, loss)
    S = np.diag([factor, factor, factor, 1.0])
    T = scene.world_to_cam.copy()
    T[:, :3, 3] *= factor
    scaled = replace(scene, world_to_cam=T, norm_to_world=S @ scene.norm_to_world)
    big = PointCloud(cloud.points_mm * factor, cloud.colors, cloud.normals, cloud.confidence)
    res = _run(scaled, big, priors, cfg, loss)
    for k, a in base.params.tensors().items():
        assert torch.allclose(a, res.params.tensors()[k], rtol=1e-3, atol=1e-4), k


def test_photo_reset_makes_a_surface_placed_in_front_transparent_and_keeps_the_true_one(problem):
    """Surfels moved 8% of their depth towards input view 0 (same colours: they look right
    in view 0, wrong in the others) are the visible surface there; the photo-consistency
    reset caps most of their opacities and none of the true surfels'."""
    scene, cloud, priors = problem
    cfg, loss = tiny_config(photo_reset={"enabled": True, "ncc_min": 0.5, "opacity": 0.01}, init_opacity=0.9)
    c0 = geometry.camera_center(scene.world_to_cam[0])
    moved = c0 + 0.92 * (cloud.points_mm - c0)
    fake = PointCloud(np.concatenate([cloud.points_mm, moved]), np.concatenate([cloud.colors, cloud.colors]),
                      np.concatenate([cloud.normals, cloud.normals]), np.ones(2 * len(cloud.points_mm)))
    params = init_from_cloud(fake, scene, replace(cfg, init_voxel_norm=0.0))
    n_true = len(cloud.points_mm)
    assert params.num == 2 * n_true  # no averaging: the rows keep the cloud's order
    trainer = Trainer(params, make_views(scene, priors, cfg, loss), cfg, loss, backend="cpu")
    n = trainer._photo_reset(cfg.densify.start_iter)
    opacity = torch.sigmoid(trainer.params.opacity_logits.detach()).numpy()
    reset = opacity <= 0.01 + 1e-6
    assert n == reset.sum() and trainer.params.num == 2 * n_true
    assert reset[n_true:].mean() > 0.6  # 0.86 when written
    assert reset[:n_true].mean() < 0.02  # 0 when written
    assert np.allclose(opacity[~reset], 0.9, atol=1e-5)


# -- training on crops ---------------------------------------------------------------------
def test_a_crop_renders_exactly_its_window_of_the_whole_view(problem):
    from pipeline.config.optimize import CropConfig
    from pipeline.optimize.views import crop_view, crop_window
    from pipeline.rasterizer import rasterize

    scene, cloud, priors = problem
    cfg, loss = tiny_config()
    params = init_from_cloud(cloud, scene, cfg)
    views = make_views(scene, priors, cfg, loss)
    full = views.at(0, 1)
    whole = rasterize(params.surfels(0), full.camera, "cpu")
    window = (13, 7, 29, 21)  # not tile-aligned, touching no border
    part = crop_view(full, *window)
    x0, y0, w, h = window
    cut = rasterize(params.surfels(0), part.camera, "cpu")
    for name in ("features", "alpha", "depth_median", "depth_expected", "normal_cam"):
        torch.testing.assert_close(getattr(cut, name), getattr(whole, name)[y0:y0 + h, x0:x0 + w], msg=name,
                                   rtol=1e-5, atol=1e-6)
    assert torch.equal(part.image, full.image[:, y0:y0 + h, x0:x0 + w])
    assert torch.equal(part.mask, full.mask[y0:y0 + h, x0:x0 + w])
    # The window lies inside the view and, with a mask, is centred on a mask pixel where it can be.
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        x0, y0, w, h = crop_window(full.size, 0.5, full.mask, g)
        assert 0 <= x0 <= full.size[1] - w and 0 <= y0 <= full.size[0] - h
        assert (w, h) == (round(0.5 * full.size[1]), round(0.5 * full.size[0]))
        assert bool(full.mask[y0:y0 + h, x0:x0 + w].any())
    with pytest.raises(ValueError, match="not inside"):
        crop_view(full, 40, 0, 30, 10)
    assert [CropConfig(0.5, 4).active_at(i) for i in range(5)] == [False, True, True, True, False]
    assert not CropConfig(1.0, 0).active_at(3) and not CropConfig(0.0, 0).active_at(3)
    with pytest.raises(ConfigError, match="optimize.crop.fraction"):
        CropConfig(1.5, 0)


def test_training_on_crops_runs_every_term_and_lowers_the_photometric_error(problem):
    from pipeline.config.optimize import CropConfig

    scene, cloud, priors = problem
    cfg, loss = tiny_config(iterations=24, surface_alpha=0.05, lambda_gcf=0.0, lambda_mv=0.1, lambda_mvgeo=0.05)
    cfg = replace(cfg, densify=replace(cfg.densify, reset_every=0), crop=CropConfig(0.5, 3),
                  start=replace(cfg.start, mv=2))
    res = _run(scene, cloud, priors, cfg, loss)
    _finite(res)
    sizes = {(r["width"], r["height"]) for r in res.history}
    assert sizes == {(scene.width, scene.height), (round(scene.width / 2), round(scene.height / 2))}
    assert any(r.get("mv_valid", 0) > 0 for r in res.history if r["width"] < scene.width)
    first = np.mean([r["l1"] for r in res.history[:3]])
    last = np.mean([r["l1"] for r in res.history[-3:]])
    assert last < first
    # L_gcf's feature maps are not cut: asking for both is a config error, before any work.
    cfg_gcf, loss_gcf = tiny_config(iterations=2, lambda_gcf=1.0)
    with pytest.raises(ConfigError, match="lambda_gcf"):
        _run(scene, cloud, priors, replace(cfg_gcf, crop=CropConfig(0.5, 0)), loss_gcf)


def test_a_crop_keeps_the_rest_of_the_remembered_source_depth(problem):
    scene, cloud, priors = problem
    cfg, loss = tiny_config()
    params = init_from_cloud(cloud, scene, cfg)
    views = make_views(scene, priors, cfg, loss)
    trainer = Trainer(params, views, cfg, loss)
    full = views.at(0, 1)
    H, W = full.size
    trainer._remember_depth(0, full, None, torch.full((H, W), 2.0))
    trainer._remember_depth(0, full, (5, 4, 10, 6), torch.full((6, 10), 3.0))
    d, K = trainer.last_depth[0]
    assert torch.equal(K, full.K) and d.shape == (H, W)
    assert float(d[4:10, 5:15].min()) == 3.0 == float(d[4:10, 5:15].max())
    assert float(d.sum()) == 2.0 * H * W + 60.0
    # A crop of a view not rendered before: no depth outside the window.
    trainer._remember_depth(1, views.at(1, 1), (0, 0, 3, 2), torch.ones((2, 3)))
    assert float(trainer.last_depth[1][0].sum()) == 6.0


def test_flat_pixels_are_computed_once_per_view_and_size_on_the_whole_view(problem, monkeypatch):
    import sys

    train_module = sys.modules["pipeline.optimize.train"]
    scene, cloud, priors = problem
    cfg, loss = tiny_config()
    loss = replace(loss, smooth_max_std=0.05)
    views = make_views(scene, priors, cfg, loss)
    trainer = Trainer(init_from_cloud(cloud, scene, cfg), views, cfg, loss)
    calls = []
    real = train_module.flat_pixels
    monkeypatch.setattr(train_module, "flat_pixels", lambda *a, **k: calls.append(1) or real(*a, **k))
    full = views.at(0, 1)
    expected = real(train_module.masked_target(full, cfg.background), 0.05)
    assert 0 < int(expected.sum()) < expected.numel()  # the test image has flat and textured pixels
    assert torch.equal(trainer._flat(0, full, None), expected)
    window = (3, 2, 17, 11)  # the crop's border pixels keep the whole view's neighbourhood
    assert torch.equal(trainer._flat(0, full, window), expected[2:13, 3:20])
    assert len(calls) == 1
    trainer._flat(0, views.at(0, 2), None)
    trainer._flat(1, full, None)
    assert len(calls) == 3


@pytest.mark.parametrize("textured", [False, True])
def test_mv_points_are_drawn_among_textured_pixels_when_asked(problem, monkeypatch, textured):
    """optimize.mv_textured_points: L_mv's reference pixels are the surface pixels within the
    incidence limit, cut to those whose reference patch is textured (losses.multiview.textured_pixels,
    computed once per view and size); off, every such pixel (the rule before it)."""
    import sys

    from pipeline.losses import multiview

    train_module = sys.modules["pipeline.optimize.train"]
    scene, cloud, priors = problem
    cfg, loss = tiny_config(mv_textured_points=textured, mv_max_points=0, lambda_mv=0.15)
    views = make_views(scene, priors, cfg, loss)
    trainer = Trainer(init_from_cloud(cloud, scene, cfg), views, cfg, loss)
    full = views.at(0, 2)
    h, w = full.size
    depth = torch.full((h, w), 2.0)
    normal = torch.zeros(h, w, 3)
    normal[..., 2] = -1.0
    surface = torch.ones(h, w, dtype=torch.bool)
    surface[:, : w // 4] = False
    seen, calls = [], []
    monkeypatch.setattr(train_module, "multiview_consistency", lambda d, n, pixels, *a, **k: seen.append(pixels))
    real = multiview.textured_pixels
    monkeypatch.setattr(train_module, "textured_pixels", lambda *a, **k: calls.append(1) or real(*a, **k))
    for _ in range(2):
        trainer._multiview(0, full.K, depth, normal, surface)
    tex = real(views.grey_full[0], h, w, loss.mv_patch, loss.mv_min_patch_std, loss.mv_ncc_gamma)
    assert 0 < int((tex & surface).sum()) < int(surface.sum())  # the test image has flat and textured pixels
    want = torch.zeros(h, w, dtype=torch.bool)
    want[seen[0][:, 1], seen[0][:, 0]] = True
    assert len(seen[0]) == int(want.sum())
    assert torch.equal(want, surface & tex if textured else surface)
    assert len(calls) == (1 if textured else 0)


def test_a_crop_weights_the_densification_statistic_by_its_share_of_the_view(problem, monkeypatch):
    import sys

    from pipeline.config.optimize import CropConfig

    train_module = sys.modules["pipeline.optimize.train"]  # the package exports the function train

    scene, cloud, priors = problem
    cfg, loss = tiny_config(lambda_gcf=0.0)
    cfg = replace(cfg, crop=CropConfig(0.5, 0))
    rendered = []
    real = train_module.rasterize
    monkeypatch.setattr(train_module, "rasterize", lambda *a, **k: rendered.append(real(*a, **k)) or rendered[-1])
    trainer = Trainer(init_from_cloud(cloud, scene, cfg), make_views(scene, priors, cfg, loss), cfg, loss)
    calls = []
    trainer.strategy.step_post_backward = lambda params, g, radii, w, h: calls.append((g.clone(), w, h))
    trainer.step()
    (g, w, h), = calls
    H, W = scene.height, scene.width
    assert (w, h) == (W, H)  # screen units of the whole view
    share = round(0.5 * W) * round(0.5 * H) / (W * H)
    assert rendered[-1].means2d.grad.abs().sum() > 0
    torch.testing.assert_close(g, rendered[-1].means2d.grad * share)
