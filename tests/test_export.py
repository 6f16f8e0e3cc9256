"""`pipeline.data.export` writes a DTU-layout scan as COLMAP (text and binary) and nerfstudio
captures that `gcgs prepare` reads back into the same cameras, images and masks, in the
layouts' own conventions (+0.5 pixel centres, OpenGL camera-to-world)."""
from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest

from pipeline import geometry
from pipeline.benchmarks import layouts
from pipeline.config.data import DataConfig
from pipeline.data import dtu, export
from pipeline.data.layouts import detect
from pipeline.data.prepare import prepare_scene
from pipeline.data.scene import SceneError
from test_layouts import H, W, _cameras, _images, write_dtu


@pytest.fixture()
def tiny_scan(tmp_path, bundled_scan):
    K, T, S = _cameras(bundled_scan)
    imgs, masks = _images(len(K))
    return write_dtu(tmp_path / "dtu", K, T, S, imgs, masks), K, T, S


def _prepare(src, out):
    return prepare_scene(src, out, DataConfig(views=[0, 2, 3], width=40, height=30))


def _points(S, n=300, seed=3):
    return S[:3, 3] + np.random.default_rng(seed).uniform(-1, 1, size=(n, 3)) * S[0, 0] * 0.3


@pytest.mark.parametrize("layout", ["colmap-text", "colmap-binary", "nerfstudio"])
def test_exported_layouts_prepare_back_to_the_same_scene(tmp_path, tiny_scan, layout):
    src_dtu, K, T, S = tiny_scan
    out = tmp_path / layout
    if layout == "nerfstudio":
        info = export.export_nerfstudio(src_dtu, out)
    else:
        info = export.export_colmap(src_dtu, out, binary=layout == "colmap-binary", points_world=_points(S))
    assert detect(out) == layout.split("-")[0] and info["views"] == [0, 1, 2, 3, 4]
    assert info["skew_dropped_px"] < 1e-9  # the fixture's cameras have no skew
    ref, got = _prepare(src_dtu, tmp_path / "ref"), _prepare(out, tmp_path / "got")

    pts = _points(S, 1000, seed=4)
    want, have = dtu.load_cameras(tmp_path / "ref"), dtu.load_cameras(tmp_path / "got")
    assert have.ids == want.ids == [0, 1, 2, 3, 4]
    for v in want.ids:
        a = geometry.project(have.K[v], have.world_to_cam[v], pts)[0]
        b = geometry.project(want.K[v], want.world_to_cam[v], pts)[0]
        np.testing.assert_allclose(a, b, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(got.images, ref.images)
    np.testing.assert_array_equal(got.masks, ref.masks)
    for v, m in dtu.load_masks(tmp_path / "ref").items():
        np.testing.assert_array_equal(dtu.load_masks(tmp_path / "got")[v], m)


def test_files_follow_the_layouts_conventions(tmp_path, tiny_scan):
    src_dtu, K, T, S = tiny_scan
    export.export_colmap(src_dtu, tmp_path / "c", binary=False, points_world=_points(S))
    rec = pycolmap.Reconstruction(str(tmp_path / "c" / "sparse" / "0"))
    im = next(i for i in rec.images.values() if i.name == "0002.png")
    fx, fy, cx, cy = rec.cameras[im.camera_id].params
    assert rec.cameras[im.camera_id].model.name == "PINHOLE"
    np.testing.assert_allclose([fx, fy, cx, cy], [K[2][0, 0], K[2][1, 1], K[2][0, 2] + 0.5, K[2][1, 2] + 0.5])
    np.testing.assert_allclose(im.cam_from_world().matrix(), T[2][:3], atol=1e-12)
    assert (tmp_path / "c" / "masks" / "0002.png.png").is_file()
    # Points seen by two images have a track of two or more: the reader's sphere uses them.
    assert sum(p.track.length() >= 2 for p in rec.points3D.values()) >= 10

    export.export_nerfstudio(src_dtu, tmp_path / "n")
    meta = json.loads((tmp_path / "n" / "transforms.json").read_text())
    f = meta["frames"][2]
    assert f["file_path"] == "images/frame_00002.png" and f["mask_path"] == "masks/frame_00002.png"
    c2w = np.array(f["transform_matrix"])
    np.testing.assert_allclose(c2w[:3, 3], geometry.camera_center(T[2]), atol=1e-9)
    np.testing.assert_allclose(c2w[:3, 2], -T[2][2, :3], atol=1e-12)  # OpenGL: the camera looks down -z
    np.testing.assert_allclose(c2w[:3, 1], -T[2][1, :3], atol=1e-12)  # and y is up
    assert f["cx"] == pytest.approx(K[2][0, 2] + 0.5) and f["w"] == W and f["h"] == H  # per frame: Ks differ


def test_skew_is_dropped_and_reported(tmp_path, bundled_scan):
    K, T, S = _cameras(bundled_scan)
    K = {v: k.copy() for v, k in K.items()}
    K[1][0, 1] = 0.02
    imgs, _ = _images(len(K))
    src = write_dtu(tmp_path / "dtu", K, T, S, imgs, None)
    info = export.export_nerfstudio(src, tmp_path / "n")
    bound = info["skew_dropped_px"]
    assert 0 < bound < 0.02
    _prepare(src, tmp_path / "ref")
    _prepare(tmp_path / "n", tmp_path / "got")
    want, have = dtu.load_cameras(tmp_path / "ref"), dtu.load_cameras(tmp_path / "got")
    pts = _points(S, 500)  # the bound holds for points inside view 1's image
    px, z = geometry.project(K[1], T[1], pts)
    inside = (z > 0) & np.all(px >= 0, 1) & (px[:, 0] <= W - 1) & (px[:, 1] <= H - 1)
    a = geometry.project(have.K[1], have.world_to_cam[1], pts[inside])[0]
    b = geometry.project(want.K[1], want.world_to_cam[1], pts[inside])[0]
    diff = np.abs(a - b).max() * 2  # prepared at half the size
    assert 0 < diff <= bound + 1e-9


def test_views_must_be_numbered_from_zero(tmp_path, bundled_scan):
    K, T, S = _cameras(bundled_scan)
    imgs, _ = _images(len(K))
    K, T, imgs = ({v + 20: d[v] for v in d} for d in (K, T, imgs))
    src = write_dtu(tmp_path / "dtu", K, T, S, imgs, None)
    with pytest.raises(SceneError, match=r"not numbered 0..4; .*view ids would change"):
        export.export_colmap(src, tmp_path / "c", binary=True)
    assert not (tmp_path / "c").exists()


def test_seen_points_keeps_points_two_cameras_see(bundled_scan):
    K, T, S = _cameras(bundled_scan)
    behind = geometry.camera_center(T[0]) - 2 * S[0, 0] * T[0][2, :3]  # behind camera 0 (and the others)
    pts = np.vstack([_points(S, 200), behind[None]])
    kept = layouts.seen_points(pts, K, T, (W, H), n=1000)
    assert 0 < len(kept) <= 200 and not np.any(np.all(np.isclose(kept, behind), 1))
    for p in kept:
        n_seen = 0
        for v in K:
            px, z = geometry.project(K[v], T[v], p[None])
            n_seen += bool(z[0] > 0 and -0.5 <= px[0, 0] < W - 0.5 and -0.5 <= px[0, 1] < H - 0.5)
        assert n_seen >= 2


@pytest.mark.slow  # imports Open3D
def test_seen_points_drops_hidden_points(bundled_scan):
    K, T, S = _cameras(bundled_scan)
    pts = _points(S, 200)
    assert len(layouts.seen_points(pts, K, T, (W, H), n=1000)) > 0
    # A wall between the cameras and the points hides them all.
    c = np.mean([geometry.camera_center(T[v]) for v in T], 0)
    n = S[:3, 3] - c
    n /= np.linalg.norm(n)
    a = np.cross(n, [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    mid, r = c + 0.5 * n * np.linalg.norm(S[:3, 3] - c), 1e4
    wall = np.array([mid + r * (s * a + t * b) for s, t in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    assert len(layouts.seen_points(pts, K, T, (W, H), n=1000, mesh=(wall, np.array([[0, 1, 2], [0, 2, 3]])))) == 0


def test_perturbed_scan_shifts_every_projection_by_the_given_pixels(tmp_path, tiny_scan):
    src, K, T, S = tiny_scan
    shifted = layouts.perturbed_scan(src, tmp_path / "shifted", 1e-3, seed=1)
    before, after = dtu.load_cameras(src), dtu.load_cameras(shifted)
    np.testing.assert_array_equal(after.norm_to_world, before.norm_to_world)
    pts = _points(S)
    directions = []
    for v in before.ids:
        a, za = geometry.project(after.K[v], after.world_to_cam[v], pts)
        b, zb = geometry.project(before.K[v], before.world_to_cam[v], pts)
        shift = a - b
        np.testing.assert_allclose(np.linalg.norm(shift, axis=1), 1e-3, rtol=1e-4)
        np.testing.assert_allclose(shift, np.broadcast_to(shift[0], shift.shape), atol=1e-8)  # one image translation
        np.testing.assert_allclose(za, zb, rtol=1e-12)
        directions.append(shift[0])
    assert np.ptp(np.asarray(directions), axis=0).max() > 1e-4  # a random direction per camera
    # images and masks are the scan's own files, not copies
    assert (shifted / "image").is_symlink() and (shifted / "image").resolve() == (src / "image").resolve()
    again = layouts.perturbed_scan(src, tmp_path / "shifted", 1e-3, seed=1)  # rerun: replaced, same cameras
    np.testing.assert_array_equal(dtu.load_cameras(again).K[0], after.K[0])


def test_skew_free_scan_drops_only_the_skew(tmp_path, bundled_scan):
    """The bundled scan's cameras carry DTU's tiny skew; the skew-free copy has none, and
    otherwise the same intrinsics, pose and sphere."""
    free = layouts.perturbed_scan(bundled_scan, tmp_path / "free", 0.0, seed=0, drop_skew=True)
    before, after = dtu.load_cameras(bundled_scan), dtu.load_cameras(free)
    assert max(abs(before.K[v][0, 1]) for v in before.ids) > 1e-6  # there was a skew to drop
    np.testing.assert_array_equal(after.norm_to_world, before.norm_to_world)
    for v in before.ids:
        assert abs(after.K[v][0, 1]) < 1e-9
        expect = before.K[v].copy()
        expect[0, 1] = 0.0
        np.testing.assert_allclose(after.K[v], expect, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(after.world_to_cam[v], before.world_to_cam[v], atol=1e-9)
