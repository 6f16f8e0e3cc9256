"""The init stage: file formats, every backend on an analytic scene, the ONNX path, the CLI
and its failure modes. Scenes are small (<= 200x150) to keep this file fast."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from init_scene import SCAN, distance_to_spheres, make_scene, ray_cast
from mast3r_helpers import FakeMASt3R, PassThrough, WrongRank, export, pair_scale
from pipeline import geometry
from pipeline.atomic import MARKER
from pipeline.cli import main
from pipeline.config.init import InitConfig
from pipeline.data.dtu import load_scene, write_scene
from pipeline.errors import ConfigError
from pipeline.geometry import voxel_downsample
from pipeline.init import mast3r, mvs, random_init, sfm
from pipeline.init.fusion import check_consistency
from pipeline.init.io import (DepthMap, InitFormatError, PointCloud, read_depth, read_ply, write_depth,
                              write_ply)
from pipeline.onnx_models import ModelError


@pytest.fixture(scope="module")
def spheres():
    return make_scene(200, 150)


@pytest.fixture(scope="module")
def mvs_result(spheres):
    return mvs.run(spheres[0], InitConfig.default())


def _write(scene, root: Path) -> Path:
    ids = scene.view_ids
    return write_scene(root, images=dict(zip(ids, scene.images)), K=dict(zip(ids, scene.K)),
                       world_to_cam=dict(zip(ids, scene.world_to_cam)), norm_to_world=scene.norm_to_world,
                       masks=dict(zip(ids, scene.masks)))


# ---------------------------------------------------------------- formats

def test_ply_round_trip_keeps_confidence(tmp_path):
    rng = np.random.default_rng(0)
    n = 50
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cloud = PointCloud(rng.normal(size=(n, 3)) * 100, rng.random((n, 3)).astype(np.float32),
                       normals.astype(np.float32), rng.random(n).astype(np.float32))
    back = read_ply(write_ply(tmp_path / "p.ply", cloud))
    np.testing.assert_allclose(back.points_mm, cloud.points_mm, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(back.normals, cloud.normals, atol=1e-6)
    np.testing.assert_allclose(back.colors, np.round(cloud.colors * 255) / 255, atol=1e-6)
    np.testing.assert_array_equal(back.confidence, cloud.confidence)
    import open3d as o3d  # other tools can read the file too
    assert len(o3d.io.read_point_cloud(str(tmp_path / "p.ply")).points) == n


def test_truncated_ply_and_corrupt_depth_name_the_file(tmp_path):
    cloud = PointCloud(np.zeros((4, 3)), np.zeros((4, 3), np.float32), np.tile([0, 0, 1.0], (4, 1)).astype(np.float32),
                       np.ones(4, np.float32))
    p = write_ply(tmp_path / "p.ply", cloud)
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(InitFormatError, match=r"p\.ply.*truncated"):
        read_ply(p)
    bad = tmp_path / "023.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(InitFormatError, match=r"023\.npz"):
        read_depth(bad)


def test_depth_round_trip_and_one_encoding_of_no_depth(tmp_path):
    d = np.full((3, 4), 500.0, np.float32)
    d[0, 0] = 0.0
    valid = d > 0
    dm = DepthMap(23, d, np.full((3, 4), 0.5, np.float32), valid, np.eye(3), np.eye(4))
    back = read_depth(write_depth(tmp_path / "023.npz", dm))
    assert back.view_id == 23 and back.depth_mm[0, 0] == 0 and back.confidence[0, 0] == 0
    assert back.depth_mm[1, 1] == 500.0 and back.valid.sum() == 11
    # "No depth" is 0 and nothing else: NaN/inf, a depth outside the mask or a masked 0 are refused.
    for bad_depth, bad_valid in ((np.where(valid, d, np.nan), valid), (np.where(valid, d, np.inf), valid),
                                 (np.full((3, 4), 500.0, np.float32), valid), (d, np.ones((3, 4), bool))):
        with pytest.raises(ValueError, match="DepthMap 23"):
            DepthMap(23, bad_depth, np.zeros((3, 4), np.float32), bad_valid, np.eye(3), np.eye(4))
    bad = tmp_path / "024.npz"
    np.savez(bad, depth_mm=np.full((3, 4), 500.0, np.float32), confidence=np.zeros((3, 4), np.float32), valid=valid,
             K=np.eye(3), world_to_cam=np.eye(4), view_id=np.int64(24))
    with pytest.raises(InitFormatError, match=r"024\.npz.*depth > 0"):
        read_depth(bad)


# ---------------------------------------------------------------- geometry pieces

def test_sphere_depth_range_brackets_the_sphere(spheres):
    scene, _ = spheres
    c = scene.norm_to_world[:3, 3]
    px, z = geometry.project(scene.K[0], scene.world_to_cam[0], c[None])
    near, far = mvs.sphere_depth_range(scene.K[0], scene.world_to_cam[0], scene.norm_to_world, px)
    # Through the centre the chord is a diameter (ray almost along z: z-extent ~ 2 r cos).
    ray = np.linalg.inv(scene.K[0]) @ np.r_[px[0], 1.0]
    cos = 1.0 / np.linalg.norm(ray)
    assert far[0] - near[0] == pytest.approx(2 * scene.norm_scale_mm * cos, rel=1e-6)
    assert near[0] < z[0] < far[0]
    near2, _ = mvs.sphere_depth_range(scene.K[0], scene.world_to_cam[0], scene.norm_to_world, np.array([[-1e5, -1e5]]))
    assert np.isnan(near2[0])


def test_consistency_rejects_a_corrupted_view(spheres):
    scene, gt = spheres
    depth = gt.astype(np.float32)
    valid = gt > 0
    depth[1] *= 1.02  # 2% off: about 13 mm at this distance
    views = check_consistency(depth, valid, scene.K, scene.world_to_cam, scene.images, InitConfig.default().consistency)
    # Views 0 and 2 agree with each other, view 1 with nobody (but a few silhouette pixels
    # whose scaled depth happens to land on the other sphere).
    assert views[1].valid.sum() < 0.01 * valid[1].sum()
    assert views[0].valid.sum() > 0.5 * valid[0].sum()
    assert views[0].count.max() == 1


def test_voxel_downsample_averages_within_voxels():
    p = np.array([[0.1, 0.1, 0.1], [0.3, 0.3, 0.3], [1.5, 0.2, 0.2]])
    a = np.array([1.0, 3.0, 5.0])
    q, b = voxel_downsample(p, 1.0, a)
    order = np.argsort(q[:, 0])
    np.testing.assert_allclose(q[order], [[0.2, 0.2, 0.2], [1.5, 0.2, 0.2]])
    np.testing.assert_allclose(b[order], [2.0, 5.0])


# ---------------------------------------------------------------- backends

def test_mvs_cloud_is_on_the_surface(spheres, mvs_result):
    scene, gt = spheres
    cloud = mvs_result.cloud
    d = distance_to_spheres(cloud.points_mm, scene)
    # 200x150: one pixel is ~1.8 mm at the object; sub-plane refinement + averaging.
    assert len(cloud) > 3000
    assert np.median(d) < 0.8, np.median(d)
    assert np.percentile(d, 90) < 3.0
    # Normals: outward sphere normals (points face the cameras).
    c, r = (scene.norm_to_world[:3, 3], 0.35 * scene.norm_scale_mm)
    on = np.abs(np.linalg.norm(cloud.points_mm - c, axis=1) - r) < 1.0
    cos = np.einsum("ij,ij->i", cloud.normals[on], (cloud.points_mm[on] - c) / r)
    assert np.median(cos) > 0.95
    assert np.all((cloud.confidence >= 0) & (cloud.confidence <= 1)) and cloud.confidence.mean() > 0.3


def test_mvs_depth_maps_are_metric_and_masked(spheres, mvs_result):
    scene, gt = spheres
    for i, dm in enumerate(mvs_result.depths):
        assert dm.view_id == scene.view_ids[i]
        assert not (dm.valid & ~scene.masks[i]).any()
        assert dm.valid.sum() > 0.5 * scene.masks[i].sum()
        rel = np.abs(dm.depth_mm[dm.valid] - gt[i][dm.valid]) / gt[i][dm.valid]
        assert np.median(rel) < 2e-3, np.median(rel)  # ~0.1 px of disparity at 200x150


def test_mvs_rejects_textureless_views(spheres):
    scene, _ = spheres
    flat = replace(scene, images=np.full_like(scene.images, 0.5))
    res = mvs.sweep_view(flat, 0, InitConfig.default().mvs)
    assert res.valid.sum() == 0


def _occluded_spheres():
    """The big test sphere and a small one in front of it on view 24's side (the big one
    first): strips of the big sphere that view 23 sees are hidden from view 24, not from 33."""
    base = load_scene(SCAN, resolution=(200, 150))
    c, r = base.norm_to_world[:3, 3], base.norm_scale_mm
    to_cam = geometry.camera_center(base.world_to_cam[1]) - c
    big, small = (c, 0.35 * r), (c + to_cam / np.linalg.norm(to_cam) * (0.35 * r + 70.0), 25.0)
    scene, gt = make_scene(200, 150, spheres=[big, small])
    return scene, gt, [big, small]


def _visible_from(scene, gt, world: np.ndarray, view: int) -> np.ndarray:
    """Whether each world point is the surface view ``view`` sees at its pixel (exact GT depth)."""
    uv, z = geometry.project(scene.K[view], scene.world_to_cam[view], world)
    u, v = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    H, W = gt.shape[1:]
    inside = (u >= 0) & (u < W) & (v >= 0) & (v < H)
    out = np.zeros(len(world), bool)
    out[inside] = np.abs(gt[view][v[inside], u[inside]] - z[inside]) < 0.01 * z[inside]
    return out


def test_best_source_matches_surface_hidden_from_one_source():
    """Beside an occluding edge the mean NCC over the sources rejects (or mismatches) the
    surface one source cannot see; the best source's NCC (less the margin) finds it, and is
    not more often wrong elsewhere."""
    scene, gt, spheres = _occluded_spheres()
    (centre, radius), H, W = spheres[0], scene.height, scene.width
    ys, xs = np.nonzero(gt[0] > 0)
    world = ray_cast(scene.K[0], scene.world_to_cam[0], H, W, spheres)[1][ys, xs]
    on_big = np.abs(np.linalg.norm(world - centre, axis=1) - radius) < 1e-3
    seen_24, seen_33 = (_visible_from(scene, gt, world, v) for v in (1, 2))
    half = on_big & ~seen_24 & seen_33
    both = on_big & seen_24 & seen_33
    assert half.sum() > 200 and both.sum() > 3000  # the scene has both kinds of pixel

    def correct_and_wrong(margin):
        sw = mvs.sweep_view(scene, 0, replace(InitConfig.default().mvs, best_source_margin=margin))
        valid = sw.valid[ys, xs]
        good = valid & (np.abs(sw.depth_mm[ys, xs] - gt[0][ys, xs]) < 0.01 * gt[0][ys, xs])
        return good, valid & ~good

    good_mean, wrong_mean = correct_and_wrong(2.0)  # NCC <= 1: the mean alone
    good_best, wrong_best = correct_and_wrong(InitConfig.default().mvs.best_source_margin)
    assert good_best[half].mean() > 0.5 and good_best[half].mean() > 2.5 * good_mean[half].mean()
    assert good_best[both].mean() > 0.9
    assert wrong_best.mean() < 1.5 * wrong_mean.mean() + 0.01


def test_negative_best_source_margin_is_named():
    with pytest.raises(ConfigError, match="best_source_margin"):
        replace(InitConfig.default().mvs, best_source_margin=-0.1)


@pytest.fixture(scope="module")
def plain_spheres():
    return make_scene(200, 150, plain=True)


def _fill_config(width: int = 100) -> InitConfig:
    """The default init config with the plain-region fill swept ``width`` pixels wide."""
    cfg = InitConfig.default()
    return replace(cfg, mvs=replace(cfg.mvs, fill_width=width))


def _fill(scene):
    """Each view's plain-region fill over its whole mask."""
    params = _fill_config().mvs
    grey = mvs.common_grey(scene.images, scene.masks)
    return [mvs.sweep_plain(scene, r, params, grey, scene.masks[r]) for r in range(scene.num_views)]


def test_plain_shaded_surface_is_found_by_the_fill(plain_spheres):
    """One albedo, Lambertian shading only: NCC matches a part (a shading ramp matches its
    own shifted copy), the absolute-difference fill most of it, at the right depth."""
    scene, gt = plain_spheres
    ncc = mvs.sweep_view(scene, 0, InitConfig.default().mvs).valid
    assert ncc.sum() < 0.5 * scene.masks[0].sum(), ncc.sum() / scene.masks[0].sum()
    for r, res in enumerate(_fill(scene)):
        assert not (res.valid & ~scene.masks[r]).any()
        assert res.valid.sum() > 0.75 * scene.masks[r].sum(), (r, res.valid.sum(), scene.masks[r].sum())
        rel = np.abs(res.depth_mm[res.valid] - gt[r][res.valid]) / gt[r][res.valid]
        # Swept at 100 px wide, where one plane (a coarse pixel of disparity) is ~1.5% of the depth.
        assert np.median(rel) < 6e-3 and np.percentile(rel, 90) < 3e-2, (np.median(rel), np.percentile(rel, 90))
        assert np.all((res.score[res.valid] >= 0) & (res.score[res.valid] <= 1))


def test_fill_ignores_exposure_and_needs_shading(plain_spheres):
    scene, _ = plain_spheres
    for a, b in zip(_fill(scene), _fill(replace(scene, images=scene.images * 0.3))):
        assert np.array_equal(a.valid, b.valid)
        np.testing.assert_allclose(a.depth_mm, b.depth_mm, rtol=1e-4)
    # One grey everywhere: every depth fits equally, so nothing is filled.
    one_grey = np.where(scene.masks[..., None], 0.5, 0.05) * np.ones(3)
    flat = replace(scene, images=one_grey.astype(np.float32))
    assert sum(r.valid.sum() for r in _fill(flat)) == 0


def test_mvs_fills_plain_regions_only_where_ncc_fails(spheres, plain_spheres, mvs_result):
    scene, _ = plain_spheres
    with_fill = mvs.run(scene, _fill_config())
    without = mvs.run(scene, _fill_config(width=0))
    assert len(without.cloud) < 0.5 * len(with_fill.cloud), (len(without.cloud), len(with_fill.cloud))
    d = distance_to_spheres(with_fill.cloud.points_mm, scene)
    coarse_px_mm = 680.0 / scene.K[0, 0, 0] * scene.width / 100  # a fill pixel at the object (~680 mm)
    assert np.median(d) < 0.5 * coarse_px_mm and np.percentile(d, 90) < 1.5 * coarse_px_mm, (
        np.median(d), np.percentile(d, 90), coarse_px_mm)
    # On a textured scene NCC matches nearly every pixel and the fill adds only what stays consistent.
    textured = mvs.run(spheres[0], _fill_config())
    assert len(textured.cloud) >= len(mvs_result.cloud)
    assert np.median(distance_to_spheres(textured.cloud.points_mm, spheres[0])) < 0.8


def test_sfm_points_are_on_the_surface(spheres):
    scene, _ = spheres
    res = sfm.run(scene, InitConfig.default())
    d = distance_to_spheres(res.cloud.points_mm, scene)
    assert len(res.cloud) > 100
    assert np.median(d) < 1.0, np.median(d)
    assert res.info["mean_reproj_px"] < 0.5 and res.depths is None


def test_random_is_uniform_in_the_unit_sphere(spheres):
    scene, _ = spheres
    cfg = InitConfig.default(random_points=20000)
    cloud = random_init.run(scene, cfg).cloud
    r = np.linalg.norm(cloud.points_mm - scene.norm_to_world[:3, 3], axis=1) / scene.norm_scale_mm
    assert len(cloud) == 20000 and r.max() <= 1.0
    assert np.mean(r**3) == pytest.approx(0.5, abs=0.02)  # uniform in volume: r^3 ~ U(0, 1)
    np.testing.assert_array_equal(random_init.run(scene, cfg).cloud.points_mm, cloud.points_mm)  # seeded


# ---------------------------------------------------------------- mast3r through onnxruntime

@pytest.fixture(scope="module")
def small_scene():
    return make_scene(160, 120)


@pytest.fixture(scope="module")
def fake_model(small_scene, tmp_path_factory):
    return export(FakeMASt3R(small_scene[0], (128, 96)), (128, 96), tmp_path_factory.mktemp("m") / "mast3r.onnx")


def test_mast3r_recovers_metric_depth(small_scene, fake_model):
    scene, gt = small_scene
    cfg = InitConfig.default()
    cfg.mast3r.model = str(fake_model)
    res = mast3r.run(scene, cfg)
    assert len(res.info["fits"]) == 6
    for f in res.info["fits"]:
        i, j = scene.view_ids.index(f["pair"][0]), scene.view_ids.index(f["pair"][1])
        assert f["scale"] == pytest.approx(1.0 / pair_scale(i, j), rel=5e-3)
    for i, dm in enumerate(res.depths):
        assert dm.valid.sum() > 0.5 * scene.masks[i].sum()
        rel = np.abs(dm.depth_mm[dm.valid] - gt[i][dm.valid]) / gt[i][dm.valid]
        assert np.median(rel) < 2e-3
    d = distance_to_spheres(res.cloud.points_mm, scene)
    assert np.median(d) < 0.6


def test_mast3r_fit_with_shift():
    rng = np.random.default_rng(1)
    zp = rng.uniform(0.5, 1.5, 400)
    zm = 600.0 * zp + 40.0
    zm[:40] *= 1.3  # outliers
    s, t, inl = mast3r.robust_fit(zp, zm, True, 200, 0.01, rng)
    assert s == pytest.approx(600.0, rel=1e-9) and t == pytest.approx(40.0, abs=1e-6)
    assert inl.sum() == 360


@pytest.mark.parametrize("module, outputs, message", [
    (PassThrough(), ("pts3d", "conf_1", "pts3d_2", "conf_2"), "missing output 'pts3d_1'"),
    (WrongRank(), ("pts3d_1", "conf_1", "pts3d_2", "conf_2"), "output 'conf_1' has rank 4"),
])
def test_mast3r_wrong_contract_is_named(small_scene, tmp_path, module, outputs, message):
    path = export(module, (128, 96), tmp_path / "bad.onnx", outputs=outputs)
    cfg = InitConfig.default()
    cfg.mast3r.model = str(path)
    with pytest.raises(ModelError, match=message):
        mast3r.run(small_scene[0], cfg)


def test_mast3r_corrupt_or_missing_model(small_scene, tmp_path):
    bad = tmp_path / "corrupt.onnx"
    bad.write_bytes(b"\x08\x07garbage" * 10)
    cfg = InitConfig.default()
    cfg.mast3r.model = str(bad)
    with pytest.raises(ModelError, match=r"corrupt\.onnx: not a loadable ONNX model"):
        mast3r.run(small_scene[0], cfg)
    cfg.mast3r.model = None
    with pytest.raises(ModelError, match="needs a MASt3R ONNX model"):
        mast3r.run(small_scene[0], cfg)


# ---------------------------------------------------------------- the CLI stage

def test_cli_mast3r_writes_everything(small_scene, fake_model, tmp_path):
    scene_dir = _write(small_scene[0], tmp_path / "scene")
    out = tmp_path / "init"
    assert main(["init", "--scene", str(scene_dir), "--backend", "mast3r", "--model", str(fake_model),
                 "--out-dir", str(out)]) == 0
    cloud = read_ply(out / "points.ply")
    assert len(cloud) > 1000
    for v in small_scene[0].view_ids:
        dm = read_depth(out / "depth" / f"{v:03d}.npz")
        assert dm.view_id == v and dm.valid.any()
    info = json.loads((out / "init.json").read_text())
    assert info["backend"] == "mast3r" and info["num_points"] == len(cloud)
    assert "time_s" not in info and "peak_rss_mb" not in info  # printed, not in the output (same bytes)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["init", "scene"]  # no temp folders left


def test_cli_bad_model_leaves_nothing(small_scene, tmp_path, capsys):
    scene_dir = _write(small_scene[0], tmp_path / "scene")
    bad = tmp_path / "m.onnx"
    bad.write_bytes(b"nope")
    out = tmp_path / "init"
    assert main(["init", "--scene", str(scene_dir), "--backend", "mast3r", "--model", str(bad),
                 "--out-dir", str(out)]) == 1
    assert "m.onnx: not a loadable ONNX model" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx", "scene"]


def test_cli_bad_scene_is_named(tmp_path, capsys):
    scene_dir = tmp_path / "scene"
    (scene_dir / "image").mkdir(parents=True)
    (scene_dir / "image" / "000000.png").write_bytes(b"not a png")
    assert main(["init", "--scene", str(scene_dir), "--backend", "sfm", "--out-dir", str(tmp_path / "o")]) == 1
    assert "no camera file" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_cli_replaces_previous_output(small_scene, tmp_path):
    scene_dir = _write(small_scene[0], tmp_path / "scene")
    out = tmp_path / "init"
    assert main(["init", "--scene", str(scene_dir), "--backend", "random", "--out-dir", str(out)]) == 0
    (out / "stale.txt").write_text("old")  # inside a folder gcgs wrote: replaced with it
    assert main(["init", "--scene", str(scene_dir), "--backend", "sfm", "--out-dir", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "init.json", "points.ply"]  # no depth for sfm


def test_mast3r_input_size_fixed_or_512_long_side(tmp_path):
    import warnings

    import torch

    from pipeline.onnx_models import load_onnx

    x = torch.zeros(1, 3, 96, 128)
    path = tmp_path / "dyn.onnx"
    dyn = {n: {2: "H", 3: "W"} for n in ("img1", "img2")}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(PassThrough().eval(), (x, x), str(path), input_names=["img1", "img2"],
                          output_names=["pts3d_1", "conf_1", "pts3d_2", "conf_2"], dynamic_axes=dyn,
                          dynamo=False, opset_version=17)
    dynamic = load_onnx(path, mast3r.MAST3R_CONTRACT)
    assert mast3r.model_size(dynamic, 800, 600, 512) == (512, 384)
    assert mast3r.model_size(dynamic, 600, 800, 512) == (384, 512)
    assert mast3r.model_size(dynamic, 1000, 600, 512) == (512, 304)  # 307.2 -> nearest multiple of 16
    fixed = export(PassThrough(), (128, 96), tmp_path / "fixed.onnx",
                   outputs=("pts3d_1", "conf_1", "pts3d_2", "conf_2"))
    assert mast3r.model_size(load_onnx(fixed, mast3r.MAST3R_CONTRACT), 800, 600, 512) == (128, 96)
