"""MVS on a dark, wide-baseline capture (issue 8): the synthetic ``synth_dark_wide`` scene
(object mean 0.06, views 6/24/40 about 40 degrees apart) must give a usable cloud, and a
run that matches little must say so (warnings in init.json and on the console).

At 800x600 (measured once, docs/init.md) the matched fractions were 18-40 % before
exposure normalisation and 57-72 % after; here the scene is rendered at 200x150."""
from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import open3d as o3d
import pytest

from pipeline import geometry
from pipeline.cli import main
from pipeline.config.init import InitConfig
from pipeline.data import dtu
from pipeline.evaluation.gt import read_mesh
from pipeline.init import mvs
from pipeline.synth import write_synth_scene

W, H = 200, 150


@pytest.fixture(scope="module")
def dark_wide(tmp_path_factory, bundled_scan):
    out = tmp_path_factory.mktemp("dark") / "synth_dark_wide"
    write_synth_scene("synth_dark_wide", out, width=W, height=H, cameras_dir=bundled_scan, log=None)
    views = json.loads((out / "scene.json").read_text())["suggested_views"]
    return out, dtu.load_scene(out, view_ids=views)


def _write(scene, root):
    ids = scene.view_ids
    return dtu.write_scene(root, images=dict(zip(ids, scene.images)), K=dict(zip(ids, scene.K)),
                           world_to_cam=dict(zip(ids, scene.world_to_cam)), norm_to_world=scene.norm_to_world,
                           masks=dict(zip(ids, scene.masks)))


def test_scene_is_dark_and_wide(dark_wide):
    _, scene = dark_wide
    mean = np.mean([scene.images[i][scene.masks[i]].mean() for i in range(scene.num_views)])
    assert 0.05 < mean < 0.07
    centre = scene.norm_to_world[:3, 3]
    dirs = [geometry.camera_center(T) - centre for T in scene.world_to_cam]
    for a, b in itertools.combinations(dirs, 2):
        angle = np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
        assert 30 < angle < 60


def test_dark_wide_baseline_gives_a_usable_cloud(dark_wide):
    root, scene = dark_wide
    res = mvs.run(scene, InitConfig.default())
    assert res.info["warnings"] == []
    # 800x600: 58-70 % matched, 15-24 % consistent (the same views, bright: the same); 20 % of
    # each view sees a part no other view sees at these baselines. Scoring by the best source
    # (init.mvs.best_source_margin) costs consistent pixels here (22-26 % with the mean alone)
    # and halves the depth outliers (docs/init.md, "Occlusions").
    assert min(res.info["matched_fraction"]) > 0.25 and min(res.info["consistent_fraction"]) > 0.12
    V, F = read_mesh(root / "gt" / "mesh.ply")
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(V.astype(np.float32), F.astype(np.uint32))
    dist = rc.compute_distance(o3d.core.Tensor(res.cloud.points_mm.astype(np.float32))).numpy()
    px_mm = 680.0 / scene.K[0, 0, 0]  # a pixel's footprint at the object (~1.9 mm)
    assert len(dist) > 2000 and np.median(dist) < 0.5 * px_mm and np.mean(dist < 2 * px_mm) > 0.85


def test_exposure_does_not_change_the_matches(dark_wide):
    """NCC ignores gain and the contrast threshold is relative to each view's exposure: the
    same views 6x brighter (one of them 8x: no pixel saturates) match the same pixels at
    the same depths."""
    _, scene = dark_wide
    assert scene.images[scene.masks].max() < 0.12
    gains = np.array([6.0, 8.0, 6.0], np.float32)[:, None, None, None]
    bright = dataclasses.replace(scene, images=scene.images * gains)
    cfg = InitConfig.default()
    a = mvs.sweep_view(scene, 1, cfg.mvs)
    b = mvs.sweep_view(bright, 1, cfg.mvs)
    assert a.valid[scene.masks[1]].mean() > 0.3 and np.mean(a.valid == b.valid) > 0.999
    both = a.valid & b.valid
    np.testing.assert_allclose(a.depth_mm[both], b.depth_mm[both], rtol=1e-4)


def test_failed_matching_is_reported(dark_wide, tmp_path, capsys):
    """A view whose image does not match the others (a failed view, like the real dark
    scan's 5-10 % matched): init still writes its outputs, but init.json lists a warning
    for that view and stderr says so in one warning line (stdout keeps the summary)."""
    _, scene = dark_wide
    good = _write(scene, tmp_path / "good")
    assert main(["init", "--scene", str(good), "--out-dir", str(tmp_path / "init_good")]) == 0
    captured = capsys.readouterr()
    out = captured.out
    info = json.loads((tmp_path / "init_good" / "init.json").read_text())
    assert info["warnings"] == [] and "warning" not in captured.err
    assert "matched/consistent fraction of mask pixels per view: 6: " in out
    assert len(info["matched_fraction"]) == len(info["consistent_fraction"]) == 3

    rng = np.random.default_rng(0)
    images = scene.images.copy()
    images[0] = rng.random(images[0].shape) * 0.12  # view 6: dark noise, unrelated to the other views
    broken = _write(dataclasses.replace(scene, images=images), tmp_path / "broken")
    assert main(["init", "--scene", str(broken), "--out-dir", str(tmp_path / "init_broken")]) == 0
    captured = capsys.readouterr()
    info = json.loads((tmp_path / "init_broken" / "init.json").read_text())
    assert info["consistent_fraction"][0] < InitConfig.default().mvs.warn_below_consistent
    assert info["warnings"] and info["warnings"][0].startswith("view 6: only ")
    warnings = [ln for ln in captured.err.splitlines() if ln.startswith("gcgs: warning: ")]
    assert len(warnings) == len(info["warnings"]) and ": view 6: only " in warnings[0]
    assert "only matched" not in captured.out
