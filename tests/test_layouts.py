"""`gcgs prepare` reads DTU, COLMAP (text and binary, via pycolmap's own writer) and
nerfstudio captures of one synthetic scene into the same cameras; bad captures give one
error naming the file; surfels export to the 3DGS viewer PLY layout."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
import torch
from plyfile import PlyData

from pipeline import geometry
from pipeline.config.data import DataConfig
from pipeline.data import dtu, export
from pipeline.data.capture import sphere_from_cameras
from pipeline.data.layouts import detect
from pipeline.data.prepare import prepare_scene
from pipeline.data.scene import SceneError
from pipeline.optimize.seed import init_params
from pipeline.surfels import THICKNESS_RATIO, splats_3dgs_attribute_names, write_splats_3dgs_ply

W, H = 80, 60
SOURCE_VIEWS = (22, 23, 24, 33, 34)  # scan24 cameras of the synthetic capture: view ids 0..4 here


REPO = Path(__file__).resolve().parents[1]


def _cameras(bundled_scan):
    """Skew-free pinhole cameras (COLMAP and nerfstudio have no skew) at W x H, and the scan's sphere."""
    cams = dtu.load_cameras(bundled_scan)
    K, T = {}, {}
    for v, src in enumerate(SOURCE_VIEWS):
        k = geometry.scale_intrinsics(cams.K[src], W / 800, H / 600)
        k[0, 1] = 0.0
        K[v], T[v] = k, cams.world_to_cam[src]
    return K, T, cams.norm_to_world


def _images(n, seed=0):
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:H, 0:W]
    imgs, masks = {}, {}
    for v in range(n):
        a, b = rng.uniform(0.05, 0.3, 2)
        img = np.stack([0.5 + 0.4 * np.sin(a * xs + v), 0.5 + 0.4 * np.cos(b * ys), np.full((H, W), v / n)], -1)
        imgs[v] = np.round(img * 255).astype(np.uint8)
        masks[v] = ((xs - W / 2 - v) / 25.0) ** 2 + ((ys - H / 2) / 18.0) ** 2 < 1
    return imgs, masks


def _write_png(path, arr):
    path.parent.mkdir(parents=True, exist_ok=True)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    elif arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    assert cv2.imwrite(str(path), arr)


def write_dtu(root, K, T, S, imgs, masks):
    root.mkdir()
    dtu.write_scene_files(root, images=imgs, K=K, world_to_cam=T, norm_to_world=S, masks=masks)
    return root


def write_colmap(root, K, T, S, imgs, masks, binary=False, mask_naming="colmap", model="PINHOLE", extra=()):
    """The capture through :func:`pipeline.data.export.write_colmap` (pycolmap's own writer),
    with 200 points around the scan's sphere centre and image ids in another order than the
    names (view ids must follow the names)."""
    rng = np.random.default_rng(1)
    points = S[:3, 3] + rng.normal(size=(200, 3)) * S[0, 0] * 0.3
    export.write_colmap(root, K, T, (W, H), imgs, masks, points, binary=binary, camera_model=model, extra_params=extra,
                        mask_naming=mask_naming, image_ids={v: 10 - v for v in K})
    return root


def write_nerfstudio(root, K, T, imgs, masks, per_frame=False, dist=None):
    """The capture through :func:`pipeline.data.export.write_nerfstudio`, its frames then
    listed in reverse order (file order must not matter)."""
    export.write_nerfstudio(root, K, T, (W, H), imgs, masks, per_frame=per_frame, distortion=dist)
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"] = meta["frames"][::-1]
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.fixture()
def scene_parts(bundled_scan):
    K, T, S = _cameras(bundled_scan)
    imgs, masks = _images(len(K))
    return K, T, S, imgs, masks


def _prepare(src, out, views=(0, 2, 3), width=40, height=30):
    return prepare_scene(src, out, DataConfig(views=list(views), width=width, height=height))


def _reprojection(scene_dir, points):
    cams = dtu.load_cameras(scene_dir)
    return {v: geometry.project(cams.K[v], cams.world_to_cam[v], points)[0] for v in cams.ids}


LAYOUTS = [
    ("colmap-text", lambda r, K, T, S, i, m: write_colmap(r, K, T, S, i, m)),
    ("colmap-binary", lambda r, K, T, S, i, m: write_colmap(r, K, T, S, i, m, binary=True, mask_naming="stem")),
    ("colmap-simple", lambda r, K, T, S, i, m: write_colmap(r, K, T, S, i, m, model="SIMPLE_PINHOLE")),
    ("nerfstudio", lambda r, K, T, S, i, m: write_nerfstudio(r, K, T, i, m)),
    ("nerfstudio-per-frame", lambda r, K, T, S, i, m: write_nerfstudio(r, K, T, i, m, per_frame=True)),
]


@pytest.mark.parametrize("with_masks", [True, False], ids=["masks", "no-masks"])
@pytest.mark.parametrize("name,write", LAYOUTS, ids=[n for n, _ in LAYOUTS])
def test_every_layout_prepares_the_same_cameras_images_and_masks(tmp_path, scene_parts, name, write, with_masks):
    K, T, S, imgs, masks = scene_parts
    if name == "colmap-simple":  # SIMPLE_PINHOLE has one focal length
        K = {v: k.copy() for v, k in K.items()}
        for k in K.values():
            k[1, 1] = k[0, 0]
    if name == "nerfstudio":  # intrinsics given once for every frame
        K = {v: K[0] for v in K}
    masks = masks if with_masks else None
    ref = _prepare(write_dtu(tmp_path / "dtu", K, T, S, imgs, masks), tmp_path / "ref")
    src = tmp_path / name
    src.mkdir()
    write(src, K, T, S, imgs, masks)
    assert detect(src) == name.split("-")[0]
    got = _prepare(src, tmp_path / "out")

    rng = np.random.default_rng(2)
    points = S[:3, 3] + rng.uniform(-1, 1, size=(100, 3)) * S[0, 0] * 0.5
    want, have = _reprojection(tmp_path / "ref", points), _reprojection(tmp_path / "out", points)
    assert sorted(have) == sorted(want) == list(range(len(SOURCE_VIEWS)))  # held-out cameras kept
    for v in want:
        np.testing.assert_allclose(have[v], want[v], atol=1e-6, rtol=0)
    # The same pictures under the same view ids, and masks for every view or none.
    assert got.view_ids == ref.view_ids == [0, 2, 3]
    np.testing.assert_array_equal(got.images, ref.images)
    again = dtu.load_scene(tmp_path / "out", view_ids=None)
    np.testing.assert_array_equal(again.images, dtu.load_scene(tmp_path / "ref", view_ids=None).images)
    if with_masks:
        np.testing.assert_array_equal(dtu.load_masks(tmp_path / "out")[1], dtu.load_masks(tmp_path / "ref")[1])
        assert sorted(dtu.load_masks(tmp_path / "out")) == list(range(5))
    else:
        assert got.masks is None and not (tmp_path / "out" / "mask").exists()
    # The derived unit sphere holds the object's centre and lies in front of every camera.
    sphere = dtu.load_cameras(tmp_path / "out").norm_to_world
    centre, r = sphere[:3, 3], sphere[0, 0]
    assert np.linalg.norm(centre - S[:3, 3]) < r
    for v in T:
        assert (T[v][:3, :3] @ centre + T[v][:3, 3])[2] > r
    meta = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert meta["layout"] == name.split("-")[0] and "scale_mat" in meta and "units" in meta


def _pattern(xs, ys):
    return 0.5 + 0.4 * np.sin(0.21 * xs) * np.cos(0.17 * ys)


def _distorted_image(K, dist):
    """An image through a lens with ``dist`` whose undistorted (pinhole ``K``) picture is _pattern."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], 1)[:, None, :]
    und = cv2.undistortPoints(pts, K, np.asarray(dist), R=None, P=K,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(H, W, 2)
    g = _pattern(und[..., 0], und[..., 1])
    return np.round(np.repeat(g[..., None], 3, -1) * 255).astype(np.uint8)


@pytest.mark.parametrize("layout", ["colmap", "nerfstudio"])
def test_distorted_images_are_undistorted_to_the_pinhole(tmp_path, scene_parts, layout):
    K, T, S, _, _ = scene_parts
    K = {v: K[0] for v in K}  # one lens
    k1, k2, p1, p2 = -0.8, 0.5, 0.01, -0.005  # pixels move by up to ~3 px at this focal length
    img = _distorted_image(K[0], [k1, k2, p1, p2])
    imgs = {v: img for v in K}
    src = tmp_path / layout
    src.mkdir()
    if layout == "colmap":
        write_colmap(src, K, T, S, imgs, None, model="OPENCV", extra=(k1, k2, p1, p2))
    else:
        write_nerfstudio(src, K, T, imgs, None, dist={"k1": k1, "k2": k2, "p1": p1, "p2": p2})
    scene = _prepare(src, tmp_path / "out", width=W, height=H)
    ys, xs = np.mgrid[0:H, 0:W]
    want = _pattern(xs, ys)
    inner = (slice(8, H - 8), slice(8, W - 8))  # the border has no source pixels after undistortion
    err = np.abs(scene.images[0][..., 0] - want)[inner]
    assert err.max() < 0.02
    # The lens matters: the distorted input is far from the pinhole picture.
    assert np.abs(img[..., 0] / 255.0 - want)[inner].max() > 0.1
    np.testing.assert_allclose(scene.K[0], K[0], atol=1e-9)  # the pinhole K, pixel centres at integers


# ---- bad input -------------------------------------------------------------------


def test_colmap_image_missing_on_disk(tmp_path, scene_parts):
    K, T, S, imgs, _ = scene_parts
    src = write_colmap(tmp_path / "c", K, T, S, imgs, None)
    (src / "images" / "0003.png").unlink()
    with pytest.raises(SceneError, match=r"sparse/0/images.txt: image '0003.png' .* is not in .*images"):
        _prepare(src, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_colmap_unknown_camera_model(tmp_path, scene_parts):
    K, T, S, imgs, _ = scene_parts
    src = write_colmap(tmp_path / "c", K, T, S, imgs, None, binary=True, model="OPENCV_FISHEYE",
                       extra=(0.01, 0.0, 0.0, 0.0))
    with pytest.raises(SceneError, match=r"sparse/0/cameras.bin: camera 1 .* model OPENCV_FISHEYE"):
        _prepare(src, tmp_path / "out")


def test_colmap_mask_missing_and_wrong_size_image(tmp_path, scene_parts):
    K, T, S, imgs, masks = scene_parts
    src = write_colmap(tmp_path / "c", K, T, S, imgs, masks)
    (src / "masks" / "0001.png.png").unlink()
    with pytest.raises(SceneError, match=r"masks: no mask for image '0001.png'"):
        _prepare(src, tmp_path / "out")
    src = write_colmap(tmp_path / "d", K, T, S, imgs, None)
    _write_png(src / "images" / "0002.png", np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(SceneError, match=r"0002.png: the image is 10x10 but its camera is for 80x60"):
        _prepare(src, tmp_path / "out")


def test_colmap_checks_of_prepare_still_apply(tmp_path, scene_parts):
    K, T, S, imgs, _ = scene_parts
    src = write_colmap(tmp_path / "c", K, T, S, imgs, None)
    with pytest.raises(SceneError, match=r"images: source images are 80x60 .* squash"):
        _prepare(src, tmp_path / "out", width=40, height=40)
    with pytest.raises(SceneError, match="at least 2"):
        _prepare(src, tmp_path / "out", views=(1,))
    with pytest.raises(SceneError, match=r"view 7 requested but the capture has views 0..4"):
        _prepare(src, tmp_path / "out", views=(0, 7))


def test_cli_prepares_a_colmap_capture_at_a_width_alone(tmp_path, scene_parts, capsys):
    from pipeline.cli import main

    K, T, S, imgs, masks = scene_parts
    src = write_colmap(tmp_path / "c", K, T, S, imgs, masks, binary=True)
    out = tmp_path / "out"
    assert main(["prepare", "--src", str(src), "--out", str(out), "--views", "0", "1", "2", "--width", "40"]) == 0
    scene = dtu.load_scene(out, view_ids=None)
    assert scene.view_ids == [0, 1, 2] and scene.images.shape == (3, 30, 40, 3) and scene.masks is not None
    # one line naming the file for bad input, through the CLI too
    (src / "images" / "0000.png").unlink()
    assert main(["prepare", "--src", str(src), "--out", str(out), "--views", "0", "1", "--width", "40"]) == 1
    assert "images.bin: image '0000.png'" in capsys.readouterr().err


@pytest.mark.parametrize("layout", ["colmap", "nerfstudio", "dtu"])
def test_prepare_trains_on_every_image_of_a_capture_and_dtus_views_of_a_dtu_scan(tmp_path, scene_parts, layout):
    """Without --views: every image of a COLMAP or nerfstudio capture (ids from 0), DTU's
    protocol views (params data.views) only for a DTU scan; --views still picks."""
    from pipeline.cli import main

    K, T, S, imgs, masks = scene_parts
    src = {"colmap": lambda: write_colmap(tmp_path / "c", K, T, S, imgs, masks),
           "nerfstudio": lambda: write_nerfstudio(tmp_path / "n", K, T, imgs, masks),
           "dtu": lambda: write_dtu(tmp_path / "d", K, T, S, imgs, masks)}[layout]()
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["data"]["views"] = [1, 3, 4]
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    common = ["--width", "40", "--params", str(tmp_path / "params.yaml")]
    assert main(["prepare", "--src", str(src), "--out", str(tmp_path / "all"), *common]) == 0
    expected = [1, 3, 4] if layout == "dtu" else sorted(range(len(imgs)))
    assert dtu.load_scene(tmp_path / "all", view_ids=None).view_ids == expected
    assert main(["prepare", "--src", str(src), "--out", str(tmp_path / "two"), "--views", "0", "2", *common]) == 0
    assert dtu.load_scene(tmp_path / "two", view_ids=None).view_ids == [0, 2]


def test_broken_colmap_model_names_the_folder(tmp_path, scene_parts):
    K, T, S, imgs, _ = scene_parts
    src = write_colmap(tmp_path / "c", K, T, S, imgs, None)
    (src / "sparse" / "0" / "cameras.txt").write_text("1 PINHOLE 80 60 50 50 x 30\n")
    with pytest.raises(SceneError, match=r"sparse/0: cannot read the COLMAP model"):
        _prepare(src, tmp_path / "out")


def test_nerfstudio_without_intrinsics(tmp_path, scene_parts):
    K, T, _, imgs, _ = scene_parts
    src = tmp_path / "n"
    write_nerfstudio(src, K, T, imgs, None)
    meta = json.loads((src / "transforms.json").read_text())
    del meta["fl_x"], meta["cy"]
    (src / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(SceneError, match=r"transforms.json: frame 'images/frame_00000.png': no intrinsics fl_x, cy"):
        _prepare(src, tmp_path / "out")


def test_nerfstudio_missing_image_and_bad_json(tmp_path, scene_parts):
    K, T, _, imgs, _ = scene_parts
    src = tmp_path / "n"
    write_nerfstudio(src, K, T, imgs, None)
    (src / "images" / "frame_00002.png").unlink()
    with pytest.raises(SceneError, match=r"transforms.json: frame 'images/frame_00002.png': file .* not found"):
        _prepare(src, tmp_path / "out")
    (src / "transforms.json").write_text("{not json")
    with pytest.raises(SceneError, match=r"transforms.json: cannot read"):
        _prepare(src, tmp_path / "out")


def test_unknown_layout_is_named(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(SceneError, match="not a known capture layout"):
        detect(tmp_path / "x")


def test_sphere_from_cameras_is_where_they_look(scene_parts):
    K, T, S, _, _ = scene_parts
    centre, r = sphere_from_cameras(K, T, (W, H))
    for v in K:
        px, z = geometry.project(K[v], T[v], centre[None])
        assert z[0] > r and abs(px[0, 0] - W / 2) < W / 4 and abs(px[0, 1] - H / 2) < H / 4
    with pytest.raises(SceneError, match="do not meet"):
        sphere_from_cameras({0: K[0]}, {0: T[0]}, (W, H))


def test_sphere_from_cameras_holds_each_views_frame(scene_parts):
    """The radius is the margin times the median over the views of the radius that holds
    the view's whole frame at the centre's distance: checked against the frame's corner rays
    by brute force (the largest distance from the centre's projection point on the axis to
    the corner rays' points at that distance along the ray)."""
    K, T, _, _, _ = scene_parts
    centre, r = sphere_from_cameras(K, T, (W, H), margin=1.0)
    corners = np.array([[-0.5, -0.5, 1.0], [W - 0.5, -0.5, 1.0], [-0.5, H - 0.5, 1.0], [W - 0.5, H - 0.5, 1.0]])
    need = []
    for v in K:
        cam = -T[v][:3, :3].T @ T[v][:3, 3]
        dist = np.linalg.norm(centre - cam)
        rays = (np.linalg.inv(K[v]) @ corners.T).T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        # The sphere of radius rho around the point `dist` along the axis touches the
        # corner ray where rho = dist * sin(angle between ray and axis).
        need.append(max(dist * math.sin(math.acos(ray[2])) for ray in rays))
    assert r == pytest.approx(float(np.median(need)), rel=1e-9)
    assert sphere_from_cameras(K, T, (W, H))[1] == pytest.approx(1.1 * r, rel=1e-12)


def test_sphere_from_cameras_refuses_axes_meeting_behind_a_camera():
    # Two cameras at x = -1 and +1, each turned outwards: their axes meet at (0, 0, -0.2), behind both.
    K = {v: np.array([[50.0, 0, 39.5], [0, 50.0, 29.5], [0, 0, 1]]) for v in (0, 1)}
    T = {}
    for v, sign in ((0, -1.0), (1, 1.0)):
        z = np.array([sign, 0.0, 0.2]) / math.hypot(1.0, 0.2)
        y = np.array([0.0, 1.0, 0.0])
        R = np.stack([np.cross(y, z), y, z])
        T[v] = np.eye(4)
        T[v][:3, :3] = R
        T[v][:3, 3] = -R @ np.array([sign, 0.0, 0.0])
    with pytest.raises(SceneError, match="behind view"):
        sphere_from_cameras(K, T, (W, H))


def test_colmap_sphere_from_points_when_the_cameras_look_in_parallel(tmp_path, scene_parts):
    """A forward-facing capture (every camera looking the same way): the cameras give no
    centre, so the COLMAP reader takes the sphere around the sparse points, and says so."""
    K, T, S, imgs, masks = scene_parts
    R = T[0][:3, :3]
    T = {v: T[0].copy() for v in K}
    for v in K:
        T[v][:3, 3] = -R @ (-R.T @ T[0][:3, 3] + np.array([20.0 * v, 0.0, 0.0]))
    src = write_colmap(tmp_path / "colmap", K, T, S, imgs, masks)
    _prepare(src, tmp_path / "out")
    meta = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert "points" in meta["scale_mat"] and "do not meet" in meta["scale_mat"]
    sphere = dtu.load_cameras(tmp_path / "out").norm_to_world
    assert np.linalg.norm(sphere[:3, 3] - S[:3, 3]) < 0.2 * S[0, 0]  # the points' median, near their centre
    with pytest.raises(SceneError, match="0 points"):
        _prepare(write_colmap_no_points(tmp_path / "empty", K, T, imgs, masks), tmp_path / "out2")


def write_colmap_no_points(root, K, T, imgs, masks):
    export.write_colmap(root, K, T, (W, H), imgs, masks, None, binary=False)
    return root


# ---- 3DGS viewer export -------------------------------------------------------------


def test_splats_3dgs_ply_has_the_viewer_layout_in_world_units(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3)) * 0.2
    normals = rng.normal(size=(50, 3))
    params = init_params(pts, normals, rng.uniform(size=(50, 3)), sh_degree=1, opacity=0.3, rng=rng)
    with torch.no_grad():
        params.log_scales[:, 1] += 0.5  # anisotropic
    S = np.diag([250.0, 250.0, 250.0, 1.0])
    S[:3, 3] = [10.0, -20.0, 600.0]
    path = write_splats_3dgs_ply(tmp_path / "splats_3dgs.ply", params, S)

    el = PlyData.read(str(path))["vertex"]
    names = [p.name for p in el.properties]
    assert names == (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                     + [f"f_rest_{i}" for i in range(9)]
                     + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert names == splats_3dgs_attribute_names(3)
    assert all(p.val_dtype in ("f4", "<f4") for p in el.properties) and len(el.data) == 50
    d = el.data
    xyz = np.stack([d["x"], d["y"], d["z"]], 1)
    np.testing.assert_allclose(xyz, pts * 250.0 + S[:3, 3], rtol=1e-6, atol=1e-3)
    ls = params.log_scales.detach().numpy().astype(np.float64) + math.log(250.0)
    np.testing.assert_allclose(d["scale_0"], ls[:, 0], atol=1e-5)
    np.testing.assert_allclose(d["scale_1"], ls[:, 1], atol=1e-5)
    np.testing.assert_allclose(d["scale_2"], ls.min(1) + math.log(THICKNESS_RATIO), atol=1e-5)
    np.testing.assert_allclose(1 / (1 + np.exp(-d["opacity"])), 0.3, atol=1e-6)  # stored as a logit
    q = np.stack([d[f"rot_{i}"] for i in range(4)], 1)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
    # w first: the third axis of the rotation is the surfel normal written in nx ny nz.
    R = np.array([[[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]] for w, x, y, z in q])
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(R[:, :, 2] * n, 1)), 1.0, atol=1e-5)
    np.testing.assert_allclose(np.stack([d["nx"], d["ny"], d["nz"]], 1), R[:, :, 2], atol=1e-5)
    sh = params.sh_dc.detach().numpy().reshape(50, 3)
    np.testing.assert_allclose(np.stack([d[f"f_dc_{i}"] for i in range(3)], 1), sh, atol=1e-6)


@pytest.mark.parametrize("layout", ["dtu", "colmap", "nerfstudio"])
def test_given_sphere_replaces_the_layouts_own(tmp_path, scene_parts, layout):
    """``--sphere`` sets the unit sphere whatever the layout gives or derives, says so in
    scene.json, and leaves the cameras alone; a bad sphere is an error naming the source
    and nothing is written."""
    K, T, S, imgs, masks = scene_parts
    src = tmp_path / layout
    if layout == "dtu":
        write_dtu(src, K, T, S, imgs, masks)
    else:
        src.mkdir()
        (write_colmap if layout == "colmap" else lambda r, K, T, S, i, m: write_nerfstudio(r, K, T, i, m))(
            src, K, T, S, imgs, masks)
    centre = S[:3, 3] + np.array([3.0, -2.0, 1.0])
    radius = 0.8 * S[0, 0]
    prepare_scene(src, tmp_path / "out", DataConfig(views=[0, 2, 3], width=40, height=30),
                  sphere=(*centre, radius))
    cams = dtu.load_cameras(tmp_path / "out")
    np.testing.assert_allclose(cams.norm_to_world[:3, 3], centre, rtol=0, atol=1e-9)
    np.testing.assert_allclose(cams.norm_to_world[:3, :3], radius * np.eye(3), rtol=1e-12, atol=0)
    for v in T:  # the cameras are what the layout gives
        np.testing.assert_allclose(cams.world_to_cam[v], T[v], rtol=0, atol=1e-9)
    meta = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert meta["scale_mat"].startswith("given (gcgs prepare --sphere)")
    for bad, match in (((*centre, 0.0), "RADIUS > 0"), ((*centre, float("nan")), "four finite numbers"),
                       ((*(2 * T[0][:3, :3].T @ -T[0][:3, 3] - centre), radius), "behind view")):
        with pytest.raises(SceneError, match=match):
            prepare_scene(src, tmp_path / "bad", DataConfig(views=[0, 2, 3], width=40, height=30), sphere=bad)
        assert not (tmp_path / "bad").exists()
