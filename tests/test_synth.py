"""Synthetic scenes: determinism, layout, camera consistency, ground truth, CLI."""
import json

import numpy as np
import pytest

from pipeline import geometry
from pipeline.cli import main as gcgs
from pipeline.data import dtu
from pipeline.evaluation.gt import read_ground_truth, read_mesh
from pipeline.synth import SCENES, Renderer, build_scene, raycast_depth, write_synth_scene

W, H = 160, 120


@pytest.fixture(scope="module")
def relief(tmp_path_factory, bundled_scan):
    out = tmp_path_factory.mktemp("synth") / "nested" / "relief"  # parent created on demand
    write_synth_scene("synth_relief", out, seed=3, width=W, height=H, cameras_dir=bundled_scan, log=None)
    return out


def test_scene_reads_back_with_all_views(relief):
    scene = dtu.load_scene(relief, view_ids=None)
    assert scene.view_ids == list(range(49))
    assert scene.images.shape == (49, H, W, 3)
    assert scene.scan_id == SCENES["synth_relief"][0]
    assert json.loads((relief / "scene.json").read_text())["seed"] == 3
    # Every view sees the object, and the ground around it (not a blank image).
    cover = scene.masks.reshape(49, -1).mean(axis=1)
    assert np.all(cover > 0.03) and np.all(cover < 0.8)
    assert np.all(scene.images[~scene.masks].std(axis=0) > 0.02)


def test_deterministic_from_seed(relief, tmp_path, bundled_scan):
    again = write_synth_scene("synth_relief", tmp_path / "a", seed=3, width=W, height=H,
                              cameras_dir=bundled_scan, log=None)
    other = write_synth_scene("synth_relief", tmp_path / "b", seed=4, width=W, height=H,
                              cameras_dir=bundled_scan, log=None)
    for v in ("000023.png", "000040.png"):
        assert (again / "image" / v).read_bytes() == (relief / "image" / v).read_bytes()
        assert (other / "image" / v).read_bytes() != (relief / "image" / v).read_bytes()
    a, b = read_mesh(again / "gt" / "mesh.ply"), read_mesh(relief / "gt" / "mesh.ply")
    np.testing.assert_array_equal(a[0], b[0])


def test_depth_reprojects_consistently_between_views(relief):
    """Back-project view 23's GT depth and check it against view 24's own depth map."""
    scene = dtu.load_scene(relief, view_ids=[23, 24])
    V, F = read_mesh(relief / "gt" / "mesh.ply")
    d23 = raycast_depth(V, F, scene.K[0], scene.world_to_cam[0], W, H)
    d24 = raycast_depth(V, F, scene.K[1], scene.world_to_cam[1], W, H)
    pts = geometry.backproject_depth(scene.K[0], scene.world_to_cam[0], np.nan_to_num(d23))[scene.masks[0]]
    px, z = geometry.project(scene.K[1], scene.world_to_cam[1], pts)
    ij = np.rint(px).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
    other = d24[ij[ok, 1], ij[ok, 0]]
    visible = np.abs(other - z[ok]) < 2.0  # mm; occluded points differ by far more
    assert visible.mean() > 0.7
    # Sub-pixel rounding moves the lookup by <= 0.5 px (~1 mm at this size on the slanted sphere).
    assert np.median(np.abs(other - z[ok])[visible]) < 0.5


def test_masks_are_object_hits_and_images_shaded(relief, bundled_scan):
    cams = dtu.load_cameras(relief)
    syn = build_scene("synth_relief", 3, dtu.load_cameras(bundled_scan))
    hits = Renderer(syn).cast(cams.K[23], cams.world_to_cam[23], W, H)
    mask = dtu.load_masks(relief, [23])[23]
    np.testing.assert_array_equal(mask, Renderer(syn).object_mask(hits))
    # Object depth is in DTU range (the cameras are ~640-690 mm from the sphere centre).
    assert 450 < np.nanmin(hits["depth"][mask]) < np.nanmax(hits["depth"][mask]) < 800


def test_ground_truth_files_are_consistent(relief):
    gt = read_ground_truth(relief / "gt")
    V, F = read_mesh(relief / "gt" / "mesh.ply")
    assert gt.scan_id == SCENES["synth_relief"][0]
    # GT points lie on the GT mesh.
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(V.astype(np.float32), F.astype(np.uint32))
    sample = gt.points_mm[:: max(1, len(gt.points_mm) // 20000)]
    dist = rc.compute_distance(o3d.core.Tensor(sample.astype(np.float32))).numpy()
    assert dist.max() < 0.01
    # The evaluation plane separates the object (above) from the ground (below).
    above = gt.above_plane(gt.points_mm)
    assert 0.2 < above.mean() < 0.95
    assert gt.obs_mask.any() and gt.res_mm > 0


def test_cli_list_and_bad_name(capsys, tmp_path):
    assert gcgs(["synth", "--list"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in SCENES)
    assert gcgs(["synth", "nope", "--out", str(tmp_path / "x")]) == 1
    assert "unknown synthetic scene 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
