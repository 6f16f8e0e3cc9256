"""Scene data layer: DTU loader/writer, resizing, and clear errors on bad input."""
import shutil

import numpy as np
import pytest

from pipeline import geometry
from pipeline.config.data import DataConfig
from pipeline.data import dtu
from pipeline.data.prepare import prepare_scene
from pipeline.data.scene import SceneError


def test_bundled_scan_loads_with_expected_cameras(bundled_scan):
    scene = dtu.load_scene(bundled_scan)
    assert scene.view_ids == [23, 24, 33]
    assert scene.images.shape == (3, 600, 800, 3) and scene.masks.shape == (3, 600, 800)
    assert scene.scan_id == 24
    # View 0 at 1600x1200 has fx 2892.3, cx 823.2 (METHOD.md); halved with integer pixel centres.
    cams = dtu.load_cameras(bundled_scan)
    assert len(cams.ids) == 49
    K0 = cams.K[0]
    assert K0[0, 0] == pytest.approx(2892.33 / 2, rel=1e-4)
    assert K0[0, 2] == pytest.approx(823.205 / 2 - 0.25, rel=1e-4)
    assert abs(K0[0, 1]) < 1e-3  # DTU's small skew is kept, not dropped
    # The object (unit sphere centre) projects inside every input view and lies in front.
    centre = scene.norm_to_world[:3, 3]
    for K, T in zip(scene.K, scene.world_to_cam):
        px, z = geometry.project(K, T, centre[None])
        assert z[0] > 0 and 0 < px[0, 0] < 800 and 0 < px[0, 1] < 600


def test_normalised_cameras_are_rigid_and_consistent(bundled_scan):
    scene = dtu.load_scene(bundled_scan)
    Tn = scene.world_to_cam_normalised()
    s = scene.norm_scale_mm
    x_norm = np.array([0.1, -0.2, 0.3])
    x_world = (scene.norm_to_world @ np.r_[x_norm, 1])[:3]
    for T, Tn_i in zip(scene.world_to_cam, Tn):
        np.testing.assert_allclose(Tn_i[:3, :3] @ Tn_i[:3, :3].T, np.eye(3), atol=1e-9)
        cam_mm = T[:3, :3] @ x_world + T[:3, 3]
        cam_norm = Tn_i[:3, :3] @ x_norm + Tn_i[:3, 3]
        np.testing.assert_allclose(cam_norm * s, cam_mm, rtol=1e-9)


def _write_synthetic(tmp_path, n=3, size=(40, 30), ids=None):
    rng = np.random.default_rng(0)
    ids = list(range(n)) if ids is None else ids
    K = np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]])
    Ks, Ts, imgs, masks = {}, {}, {}, {}
    for v in ids:
        T = np.eye(4)
        T[:3, 3] = [v * 10.0, 0, 500.0]
        Ks[v], Ts[v] = K, T
        imgs[v] = rng.uniform(size=(size[1], size[0], 3))
        m = np.zeros((size[1], size[0]), bool)
        m[5:20, 5:30] = True
        masks[v] = m
    S = np.diag([100.0, 100.0, 100.0, 1.0])
    return dtu.write_scene(tmp_path / "scan", imgs, Ks, Ts, S, masks=masks, meta={"name": "toy", "scan_id": 5})


def test_write_then_load_roundtrip_reprojects_known_points(tmp_path):
    root = _write_synthetic(tmp_path)
    scene = dtu.load_scene(root, view_ids=None)
    assert scene.view_ids == [0, 1, 2] and scene.scan_id == 5 and scene.name == "toy"
    pts = np.array([[0.0, 0, 0], [3, -2, 10], [-5, 4, -20]])
    for v in range(3):
        T = np.eye(4)
        T[:3, 3] = [v * 10.0, 0, 500.0]
        want, _ = geometry.project(np.array([[50.0, 0, 19.5], [0, 50.0, 14.5], [0, 0, 1]]), T, pts)
        got, _ = geometry.project(scene.K[v], scene.world_to_cam[v], pts)
        np.testing.assert_allclose(got, want, atol=1e-9)


def test_resize_scales_K_and_masks_consistently(tmp_path):
    root = _write_synthetic(tmp_path, size=(40, 30))
    full = dtu.load_scene(root, view_ids=None)
    half = dtu.load_scene(root, view_ids=None, resolution=(20, 15))
    assert half.images.shape == (3, 15, 20, 3) and half.masks.shape == (3, 15, 20)
    # A point at full-res pixel centre (x, y) lands at half-res 0.5 (x + 0.5) - 0.5.
    pt = geometry.backproject_depth(full.K[0], full.world_to_cam[0], np.full((30, 40), 400.0))[9, 13]
    px, _ = geometry.project(half.K[0], half.world_to_cam[0], pt[None])
    np.testing.assert_allclose(px[0], [0.5 * 13.5 - 0.5, 0.5 * 9.5 - 0.5], atol=1e-9)
    # Mask rows 5..19, cols 5..29 at full res -> half res about rows 2.5..9.5, cols 2.5..14.5.
    assert half.masks[0, 5, 8] and not half.masks[0, 12, 8]


def test_prepare_keeps_all_cameras_and_masks(tmp_path, bundled_scan):
    out = tmp_path / "prepared"
    scene = prepare_scene(bundled_scan, out, DataConfig(views=[23, 33], width=400, height=300))
    assert scene.view_ids == [23, 33]
    cams = dtu.load_cameras(out)
    assert len(cams.ids) == 49
    assert len(dtu.load_masks(out)) == 49
    again = dtu.load_scene(out, view_ids=None)
    assert again.view_ids == [23, 33] and again.images.shape == (2, 300, 400, 3)
    np.testing.assert_allclose(again.K, scene.K, atol=1e-9)


def _scan_in_size(tmp_path, width, height, n_views=12):
    """A scan of ``n_views`` views (ids 0..n-1) with images and masks of ``width x height``."""
    rng = np.random.default_rng(1)
    K = np.array([[1.2 * width, 0, (width - 1) / 2], [0, 1.2 * width, (height - 1) / 2], [0, 0, 1]])
    ids = list(range(n_views))
    Ts = {}
    for v in ids:
        T = np.eye(4)
        T[:3, 3] = [v * 10.0 - 50.0, 0, 500.0]
        Ts[v] = T
    mask = np.zeros((height, width), bool)
    mask[height // 4:3 * height // 4, width // 4:3 * width // 4] = True
    return dtu.write_scene(tmp_path / "src", {v: rng.uniform(size=(height, width, 3)) for v in ids},
                           {v: K for v in ids}, Ts, np.diag([100.0, 100.0, 100.0, 1.0]),
                           masks={v: mask for v in ids}, meta={"name": "toy", "scan_id": 7})


@pytest.mark.parametrize("views", [[0, 1, 2], [0, 1], [0, 2, 5], [3, 7, 11], [11, 4]])
def test_prepare_then_load_round_trip_for_any_views(tmp_path, views):
    src = _scan_in_size(tmp_path, 80, 60)
    out = tmp_path / "prepared"
    prepared = prepare_scene(src, out, DataConfig(views=views, width=40, height=30))
    again = dtu.load_scene(out, view_ids=None)
    assert again.view_ids == sorted(views) == sorted(prepared.view_ids)
    order = [prepared.view_ids.index(v) for v in again.view_ids]
    np.testing.assert_allclose(again.K, prepared.K[order], atol=1e-9)
    np.testing.assert_array_equal(again.world_to_cam, prepared.world_to_cam[order])
    assert len(dtu.load_cameras(out).ids) == 12  # held-out cameras are kept


def test_prepare_cli_views_and_init_read_back(tmp_path, capsys):
    """`gcgs prepare --views 0 1 2` then `gcgs init` on it (the reported failure)."""
    from pipeline.cli import main

    src = _scan_in_size(tmp_path, 80, 60)
    out = tmp_path / "prepared"
    assert main(["prepare", "--src", str(src), "--out", str(out), "--views", "0", "1", "2", "--width", "40"]) == 0
    assert "views [0, 1, 2] at 40x30" in capsys.readouterr().out
    rc = main(["init", "--scene", str(out), "--backend", "random", "--out-dir", str(tmp_path / "init")])
    assert rc == 0, capsys.readouterr().err
    assert (tmp_path / "init" / "points.ply").is_file()


def test_prepare_no_masks_leaves_the_sources_masks_out(tmp_path, capsys):
    """`--no-masks --masks none`: the scene is written as from a capture without masks, and
    none are derived (docs/inputs.md)."""
    import json

    from pipeline.cli import main

    src = _scan_in_size(tmp_path, 80, 60)
    out = tmp_path / "prepared"
    assert main(["prepare", "--src", str(src), "--out", str(out), "--views", "0", "1", "--width", "40",
                 "--no-masks", "--masks", "none"]) == 0
    assert "no masks" in capsys.readouterr().out
    assert dtu.load_scene(out, view_ids=None).masks is None and not (out / "mask").exists()
    assert json.loads((out / "scene.json").read_text())["masks_ignored"] is True
    with_masks = prepare_scene(src, tmp_path / "masked", DataConfig(views=[0, 1], width=40, height=30))
    assert with_masks.masks is not None


def test_prepare_keeps_the_aspect_ratio_of_a_5_4_source(tmp_path, capsys):
    """A 1280x1024 (5:4) source: the default 800x600 (4:3) is refused with a message
    naming the file and both ratios; --width alone derives the height."""
    from pipeline.cli import main
    from pipeline.data.prepare import check_aspect

    src = _scan_in_size(tmp_path, 1280, 1024, n_views=3)
    out = tmp_path / "prepared"
    assert main(["prepare", "--src", str(src), "--out", str(out), "--views", "0", "1"]) == 1
    err = capsys.readouterr().err
    assert "image: source images are 1280x1024 (aspect 1.250)" in err
    assert "training size 800x600 has aspect 1.333" in err and "Traceback" not in err
    assert not out.exists()
    assert main(["prepare", "--src", str(src), "--out", str(out), "--views", "0", "1", "--width", "800"]) == 0
    scene = dtu.load_scene(out, view_ids=None)
    assert scene.images.shape == (2, 640, 800, 3)
    # The scaled intrinsics keep square pixels: fx/fy as in the source.
    assert scene.K[0, 0, 0] / scene.K[0, 1, 1] == pytest.approx(1.0)
    # Sizes within a pixel of rounding are not a change of aspect; more is.
    check_aspect(src, (1280, 1024), 801, 641)
    with pytest.raises(SceneError, match="squash"):
        check_aspect(src, (1280, 1024), 800, 642)


# ---- bad input -------------------------------------------------------------------


def test_missing_directory_and_files(tmp_path):
    with pytest.raises(SceneError, match="not found"):
        dtu.load_scene(tmp_path / "nope")
    (tmp_path / "a").mkdir()
    with pytest.raises(SceneError, match="no image directory"):
        dtu.load_scene(tmp_path / "a")
    root = _write_synthetic(tmp_path)
    (root / "cameras_sphere.npz").unlink()
    with pytest.raises(SceneError, match="no camera file"):
        dtu.load_scene(root, view_ids=None)


def test_extra_cameras_are_held_out_views_when_images_are_numbered(tmp_path):
    """Images 0..k-1 with cameras for more views (what `gcgs prepare --views 0 1 2` writes)
    are views 0..k-1, not a full scan missing cameras."""
    root = _write_synthetic(tmp_path)
    data = dict(np.load(root / "cameras_sphere.npz"))
    data["world_mat_7"] = data["world_mat_0"]
    data["scale_mat_7"] = data["scale_mat_0"]
    np.savez(root / "cameras_sphere.npz", **data)
    assert dtu.load_scene(root, view_ids=None).view_ids == [0, 1, 2]


def test_camera_count_must_match_images_matched_by_index(tmp_path):
    """Images without numbers in their names are matched to cameras by sorted index
    (NeuS): then a different camera count means the pairing is unknown."""
    root = _write_synthetic(tmp_path)
    for i, name in enumerate("abc"):
        (root / "image" / f"{i:06d}.png").rename(root / "image" / f"{name}.png")
    assert dtu.load_scene(root, view_ids=None).view_ids == [0, 1, 2]
    data = dict(np.load(root / "cameras_sphere.npz"))
    data["world_mat_7"] = data["world_mat_0"]
    data["scale_mat_7"] = data["scale_mat_0"]
    np.savez(root / "cameras_sphere.npz", **data)
    with pytest.raises(SceneError, match=r"camera count \(4\) does not match image count \(3\)"):
        dtu.load_scene(root, view_ids=None)


def test_image_without_camera(tmp_path):
    root = _write_synthetic(tmp_path, ids=[3, 5])
    shutil.copy(root / "image" / "000003.png", root / "image" / "000009.png")
    with pytest.raises(SceneError, match=r"no world_mat for image\(s\) \[9\]"):
        dtu.load_scene(root, view_ids=None)


@pytest.mark.parametrize("value, pattern", [(np.nan, "non-finite"), (0.0, "singular")])
def test_bad_camera_matrix_names_file_and_entry(tmp_path, value, pattern):
    root = _write_synthetic(tmp_path)
    data = dict(np.load(root / "cameras_sphere.npz"))
    data["world_mat_1"] = np.full((4, 4), value)
    np.savez(root / "cameras_sphere.npz", **data)
    with pytest.raises(SceneError, match=rf"cameras_sphere.npz: world_mat_1: .*{pattern}"):
        dtu.load_scene(root, view_ids=None)


def test_corrupt_image(tmp_path):
    root = _write_synthetic(tmp_path)
    (root / "image" / "000001.png").write_bytes(b"not a png")
    with pytest.raises(SceneError, match=r"000001.png: not a readable image"):
        dtu.load_scene(root, view_ids=None)


def test_wrongly_sized_image_and_mask(tmp_path):
    import cv2

    root = _write_synthetic(tmp_path)
    cv2.imwrite(str(root / "image" / "000002.png"), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(SceneError, match=r"000002.png: size 10x10 differs"):
        dtu.load_scene(root, view_ids=None)
    root = _write_synthetic(tmp_path / "b")
    cv2.imwrite(str(root / "mask" / "001.png"), np.full((10, 10), 255, np.uint8))
    with pytest.raises(SceneError, match=r"001.png: mask size 10x10 differs from image size 40x30"):
        dtu.load_scene(root, view_ids=None)


def test_empty_and_missing_mask(tmp_path):
    import cv2

    root = _write_synthetic(tmp_path)
    cv2.imwrite(str(root / "mask" / "000.png"), np.zeros((30, 40), np.uint8))
    with pytest.raises(SceneError, match=r"000.png: mask is empty"):
        dtu.load_scene(root, view_ids=None)
    (root / "mask" / "000.png").unlink()
    with pytest.raises(SceneError, match="no mask for view 0"):
        dtu.load_scene(root, view_ids=None)


def test_requested_view_missing(tmp_path):
    root = _write_synthetic(tmp_path)
    with pytest.raises(SceneError, match="view 23 requested"):
        dtu.load_scene(root, view_ids=[23])


def test_write_scene_leaves_nothing_on_failure(tmp_path):
    bad = {0: np.zeros((4, 4, 3))}
    with pytest.raises(KeyError):  # a camera without its pose fails after the images are written
        dtu.write_scene(tmp_path / "out", bad, K={0: np.eye(3)}, world_to_cam={}, norm_to_world=np.eye(4))
    assert list(tmp_path.iterdir()) == []
