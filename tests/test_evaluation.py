"""The DTU Chamfer protocol: self/offset/far-away meshes, bad meshes, culling, and the CLI."""
import json
import shutil

import cv2
import numpy as np
import open3d as o3d
import pytest

from pipeline import geometry
from pipeline.cli import main
from pipeline.config.evaluate import EvaluateConfig
from pipeline.data import dtu
from pipeline.evaluation import dtu_eval, gt as gtmod
from pipeline.evaluation.sampling import MeshError, sample_mesh

CENTRE = np.array([-28.0, -13.0, 641.0])  # scan24's object centre (DTU world, mm)
RADIUS = 50.0  # a DTU-object-sized ball, 100 mm across
# Cameras sit at smaller z (DTU-like); the ground cuts the far cap (z > centre + 40).
PLANE = np.array([0.0, 0.0, -1.0, CENTRE[2] + 40.0])
NO_CULL = EvaluateConfig.default(cull_views="none")


def sphere(radius=RADIUS, centre=CENTRE, resolution=60):
    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    m.compute_vertex_normals()
    return np.asarray(m.vertices) + centre, np.asarray(m.triangles), np.asarray(m.vertex_normals)


@pytest.fixture(scope="module")
def ground_truth(tmp_path_factory):
    V, F, _ = sphere()
    root = tmp_path_factory.mktemp("gt")
    gtmod.write_ground_truth(root, 1001, V, F, PLANE)
    return gtmod.read_ground_truth(root)


def look_at(centre, target, up=(0.0, -1.0, 0.0)):
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z])
    T[:3, 3] = -T[:3, :3] @ centre
    return T


def ball_mask(K, T, shape, centre=CENTRE, radius=RADIUS):
    """Exact silhouette of a ball: pixels whose ray passes within ``radius`` of its centre."""
    H, W = shape
    ys, xs = np.mgrid[0:H, 0:W]
    rays = np.stack([xs, ys, np.ones_like(xs)], -1).reshape(-1, 3) @ np.linalg.inv(K).T @ T[:3, :3]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    c = centre - geometry.camera_center(T)
    dist = np.linalg.norm(c - (rays @ c)[:, None] * rays, axis=1)
    return (dist < radius).reshape(H, W)


def synthetic_views(shape=(120, 160)):
    """Three cameras 500 mm from the ball, about 25 degrees apart, with exact masks."""
    H, W = shape
    K = np.array([[150.0, 0, (W - 1) / 2], [0, 150.0, (H - 1) / 2], [0, 0, 1]])
    views = []
    for i, ang in enumerate(np.radians([-25.0, 0.0, 25.0])):
        C = CENTRE + 500 * np.array([np.sin(ang), 0.0, -np.cos(ang)])
        T = look_at(C, CENTRE)
        views.append(dtu_eval.CullView(view_id=i, K=K, world_to_cam=T, mask=ball_mask(K, T, shape)))
    return views


# --- the protocol ---------------------------------------------------------------------------


def test_gt_mesh_against_itself_is_near_zero(ground_truth):
    V, F, _ = sphere()
    # The GT was written with seed 0 and is evaluated with seed 0, yet its points are
    # thinned in another order (derived seed): the score is the true discretisation
    # floor (~0.07 mm), not ~1e-5 mm from getting the GT points themselves back.
    m = dtu_eval.evaluate_mesh(V, F, ground_truth, NO_CULL, seed=0, log=None)
    assert m["valid"] and m["problems"] == []
    assert 0.03 < m["accuracy_mm"] < 0.12 and 0.03 < m["completeness_mm"] < 0.12
    assert m["overall_mm"] == pytest.approx((m["accuracy_mm"] + m["completeness_mm"]) / 2)
    c = m["counts"]
    assert c["data_sampled"] > c["data_downsampled"] >= c["data_in_bb"] >= c["data_in_obs"] > 0.9 * c["data_downsampled"]
    assert c["gt_points"] > c["gt_above_plane"] == c["completeness_used"] > 0.8 * c["gt_points"]
    assert m["fraction_beyond_max_dist"] == {"accuracy": 0.0, "completeness": 0.0}


@pytest.mark.parametrize("delta", [0.5, 2.0, -2.0])
def test_offset_along_normals_gives_delta(ground_truth, delta):
    V, F, N = sphere()
    m = dtu_eval.evaluate_mesh(V + delta * N, F, ground_truth, NO_CULL, log=None)
    assert m["accuracy_mm"] == pytest.approx(abs(delta), rel=0.1)
    assert m["completeness_mm"] == pytest.approx(abs(delta), rel=0.1)


def test_by_distance_bands_add_up_to_the_mean():
    d = np.array([0.1, 0.2, 0.7, 1.5, 3.0, 7.0, 25.0, np.inf])  # the last two are beyond max_dist
    bands = dtu_eval.by_distance(d, 20.0)
    assert list(bands) == ["0-0.5", "0.5-1", "1-2", "2-5", "5-20"]
    used = d[d < 20.0]
    assert [b["fraction"] for b in bands.values()] == pytest.approx([2 / 6, 1 / 6, 1 / 6, 1 / 6, 1 / 6])
    assert bands["5-20"]["share_mm"] == pytest.approx(7.0 / 6)
    assert sum(b["share_mm"] for b in bands.values()) == pytest.approx(used.mean())
    assert list(dtu_eval.by_distance(d, 1.5)) == ["0-0.5", "0.5-1", "1-1.5"]  # bands end at max_dist


@pytest.mark.parametrize("delta", [0.7, 3.0])
def test_offset_mesh_falls_in_its_distance_band(ground_truth, delta):
    V, F, N = sphere()
    m = dtu_eval.evaluate_mesh(V + delta * N, F, ground_truth, NO_CULL, log=None)
    band = "0.5-1" if delta < 1 else "2-5"
    for side in ("accuracy", "completeness"):
        assert m[f"{side}_by_distance"][band]["fraction"] > 0.9
        assert sum(b["share_mm"] for b in m[f"{side}_by_distance"].values()) == pytest.approx(m[f"{side}_mm"])


def test_far_distances_are_left_out_not_clamped(tmp_path):
    V, F, _ = sphere(resolution=30)
    # Observe the whole box around the ball, so that the floater below counts for accuracy.
    grid = np.stack(np.meshgrid(*[np.arange(-90.0, 91.0, 10.0)] * 3, indexing="ij"), -1).reshape(-1, 3) + CENTRE
    gtmod.write_ground_truth(tmp_path, 3, V, F, PLANE, observed_points_mm=grid)
    g = gtmod.read_ground_truth(tmp_path)
    Vf, Ff, _ = sphere(radius=10.0, centre=CENTRE + [0, 0, -RADIUS - 35.0], resolution=20)  # 25+ mm off
    both_V = np.concatenate([V, Vf])
    both_F = np.concatenate([F, Ff + len(V)])
    m = dtu_eval.evaluate_mesh(both_V, both_F, g, NO_CULL, seed=1, log=None)
    n_out = m["counts"]["data_in_obs"] - m["counts"]["accuracy_used"]
    assert n_out > 10000  # the floater is observed, and every one of its points is >= 20 mm away
    frac = m["fraction_beyond_max_dist"]["accuracy"]
    assert frac == pytest.approx(n_out / m["counts"]["data_in_obs"])
    # Left out of the mean: it stays at the self-evaluation level; clamping would add 20 * frac.
    assert 20 * frac > 0.5 and m["accuracy_mm"] < 0.12 and m["completeness_mm"] < 0.12


def test_far_away_mesh_is_reported_undefined(ground_truth):
    V, F, _ = sphere(resolution=20)
    m = dtu_eval.evaluate_mesh(V + [1000.0, 0, 0], F, ground_truth, NO_CULL, log=None)
    assert not m["valid"]
    assert np.isnan(m["accuracy_mm"]) and np.isnan(m["completeness_mm"]) and np.isnan(m["overall_mm"])
    assert m["counts"]["data_in_bb"] == 0 and m["counts"]["accuracy_used"] == 0
    assert m["counts"]["completeness_used"] == 0 and m["fraction_beyond_max_dist"]["completeness"] == 1.0
    assert any("bounding box" in p for p in m["problems"]) and any("accuracy undefined" in p for p in m["problems"])
    # A mesh in the normalised frame (unit sphere) gets a hint.
    m = dtu_eval.evaluate_mesh(V / 100.0, F, ground_truth, NO_CULL, log=None)
    assert any("normalised frame" in p for p in m["problems"])


def test_bounding_box_patch_is_60_below_and_120_above(ground_truth):
    bb = ground_truth.bb_mm
    # 0.1 mm triangles: each leaves exactly one point after the 0.2 mm downsampling.
    corners = [bb[1] + [0, 0, 90.0], bb[1] + [0, 0, 130.0], bb[0] - [0, 0, 50.0], bb[0] - [0, 0, 70.0]]
    V = np.concatenate([c + np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]) for c in corners])
    F = np.arange(len(V)).reshape(-1, 3)
    m = dtu_eval.evaluate_mesh(V, F, ground_truth, NO_CULL, log=None)
    assert m["counts"]["data_downsampled"] == 4 and m["counts"]["data_in_bb"] == 2


@pytest.mark.parametrize(
    "V, F, match",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "no vertices"),
        (np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2.0]]) + CENTRE, np.array([[0, 1, 2]]), "zero area"),
    ],
)
def test_empty_or_degenerate_mesh_is_an_error(ground_truth, V, F, match):
    with pytest.raises(MeshError, match=match):
        dtu_eval.evaluate_mesh(V, F, ground_truth, NO_CULL, log=None)


def test_bad_parameters_are_rejected(ground_truth):
    V, F, _ = sphere(resolution=10)
    with pytest.raises(ValueError, match="sample_spacing_mm"):
        dtu_eval.evaluate_mesh(V, F, ground_truth, EvaluateConfig.default(cull_views="none", sample_spacing_mm=0), log=None)


# --- culling --------------------------------------------------------------------------------


def test_dilation_disk_radius():
    m = np.zeros((41, 41), bool)
    m[20, 20] = True
    d = dtu_eval.dilate_mask(m, 12.0)
    assert d[20, 32] and not d[20, 33] and d[28, 28] and not d[28, 29]  # 8^2+8^2 <= 144 < 8^2+9^2


def test_culling_removes_what_is_outside_the_masks(ground_truth):
    views = synthetic_views()
    V, F, _ = sphere(resolution=30)
    # A second ball beside the first: inside every image, outside every mask.
    Vd, Fd, _ = sphere(radius=10.0, centre=CENTRE + [0, 110.0, 0], resolution=10)
    for v in views:
        px, z = geometry.project(v.K, v.world_to_cam, Vd)
        assert (z > 0).all() and (px > 0).all() and (px[:, 0] < 159).all() and (px[:, 1] < 119).all()
    all_V = np.concatenate([V, Vd])
    keep = dtu_eval.cull_vertices(all_V, views, dilation_px_at_1600=24.0)
    assert keep[: len(V)].all() and not keep[len(V):].any()
    # A view that does not see the distractor (it projects outside its image) does not cull it.
    zoomed = views[1].K @ np.diag([3.0, 3.0, 1.0])  # 3x focal length, same centre
    zoomed[:2, 2] = views[1].K[:2, 2]
    narrow = dtu_eval.CullView(view_id=9, K=zoomed, world_to_cam=views[1].world_to_cam, mask=views[1].mask)
    assert dtu_eval.cull_vertices(Vd, [narrow], 24.0).all()
    # Through evaluate_mesh: counts say what was culled, and the metrics are the clean ones.
    m = dtu_eval.evaluate_mesh(all_V, np.concatenate([F, Fd + len(V)]), ground_truth,
                               EvaluateConfig.default(), views=views, log=None)
    assert m["counts"]["culled_vertices"] == len(V) and m["counts"]["culled_triangles"] == len(F)
    assert m["config"]["cull_view_ids"] == [0, 1, 2] and m["accuracy_mm"] < 0.15


def test_culling_everything_is_reported(ground_truth):
    views = synthetic_views()
    Vd, Fd, _ = sphere(radius=10.0, centre=CENTRE + [0, 110.0, 0], resolution=10)
    m = dtu_eval.evaluate_mesh(Vd, Fd, ground_truth, EvaluateConfig.default(), views=views, log=None)
    assert not m["valid"] and any("culling removed every vertex" in p for p in m["problems"])


def test_cull_views_from_the_bundled_scan_and_low_resolution_masks(bundled_scan, tmp_path):
    views = dtu_eval.load_cull_views(bundled_scan, "input", [23, 24, 33])
    assert [v.view_id for v in views] == [23, 24, 33] and views[0].mask.shape == (600, 800)
    assert len(dtu_eval.load_cull_views(bundled_scan, "all", [23])) == 49
    assert dtu_eval.load_cull_views(bundled_scan, "none", [23]) == []
    # Points of the scan's bounding sphere: the three input views drop some; all 49 views
    # drop those and more (a vertex must pass every view that sees it).
    S = dtu.load_cameras(bundled_scan).norm_to_world
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(20000, 3))
    pts = (pts[np.linalg.norm(pts, axis=1) < 1] * S[0, 0]) + S[:3, 3]
    keep = dtu_eval.cull_vertices(pts, views, 24.0)
    keep_all = dtu_eval.cull_vertices(pts, dtu_eval.load_cull_views(bundled_scan, "all", [23]), 24.0)
    assert 0.05 < keep.mean() < 0.95 and keep_all.mean() < keep.mean() - 0.2 and not (keep_all & ~keep).any()
    # The same masks stored at half size: cameras are rescaled and the result barely changes.
    small = tmp_path / "scan"
    shutil.copytree(bundled_scan, small)
    for p in (small / "mask").iterdir():
        m = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(p), cv2.resize(m, (400, 300), interpolation=cv2.INTER_AREA))
    half = dtu_eval.load_cull_views(small, "input", [23, 24, 33])
    assert half[0].mask.shape == (300, 400)
    np.testing.assert_allclose(half[0].K[0, 0], views[0].K[0, 0] / 2)
    assert (dtu_eval.cull_vertices(pts, half, 24.0) == keep).mean() > 0.99


# --- against a transcription of the public script ---------------------------------------------


def script_cull(V, views, dilation=24.0):
    """2DGS's cull_scan: torch grid_sample (nearest, align_corners) of the dilated masks."""
    import scipy.ndimage
    import torch

    hom = torch.from_numpy(np.c_[V, np.ones(len(V))].T)
    sampled = []
    for v in views:
        H, W = v.mask.shape
        cam = torch.from_numpy(v.K @ v.world_to_cam[:3]) @ hom
        pix = (cam[:2] / (cam[2:] + 1e-6)).T.clone()
        pix[:, 0] /= W - 1
        pix[:, 1] /= H - 1
        pix = (pix - 0.5) * 2
        valid = ((pix > -1.0) & (pix < 1.0)).all(dim=-1).double()
        r = dilation * W / 1600  # skimage's disk(r): x^2 + y^2 <= r^2
        yy, xx = np.mgrid[-int(r): int(r) + 1, -int(r): int(r) + 1]
        dil = scipy.ndimage.binary_dilation(v.mask, structure=xx**2 + yy**2 <= r**2)
        grid = torch.nn.functional.grid_sample(torch.from_numpy(dil).double()[None, None], pix[None, None],
                                               mode="nearest", padding_mode="zeros", align_corners=True)
        sampled.append(grid[0, -1, 0] + (1.0 - valid))
    return (torch.stack(sampled, -1) > 0).all(dim=-1).numpy()


def public_script(V, F, views, gt_root, scan, seed, thresh=0.2, patch=60.0, max_dist=20.0):
    """The 2DGS culling + DTU eval.py steps, written the script's way (per-triangle grids,
    KD-tree radius lists), with sklearn's KD-tree replaced by scipy's and the unseeded
    shuffle replaced by the seeded permutation."""
    import scipy.io
    from scipy.spatial import cKDTree
    from test_evaluation_gt import script_triangle_samples

    keep = script_cull(V, views)
    faces = F[keep[F].all(axis=1)]
    remap = np.cumsum(keep) - 1
    Vk, Fk = V[keep], remap[faces]

    pts = [script_triangle_samples(*Vk[f], thresh) for f in Fk]
    data = np.concatenate([Vk, *pts])[np.random.default_rng(seed).permutation(len(Vk) + sum(map(len, pts)))]
    mask = np.ones(len(data), dtype=bool)
    for curr, idxs in enumerate(cKDTree(data).query_ball_point(data, thresh)):
        if mask[curr]:
            mask[idxs] = False
            mask[curr] = True
    data_down = data[mask]

    obs = scipy.io.loadmat(f"{gt_root}/ObsMask/ObsMask{scan}_10.mat")
    ObsMask, BB, Res = obs["ObsMask"], obs["BB"].astype(np.float32), obs["Res"]
    inbound = ((data_down >= BB[:1] - patch) & (data_down < BB[1:] + patch * 2)).sum(axis=-1) == 3
    data_in = data_down[inbound]
    grid = np.around((data_in - BB[:1]) / Res).astype(np.int32)
    grid_inbound = ((grid >= 0) & (grid < np.expand_dims(ObsMask.shape, 0))).sum(axis=-1) == 3
    g = grid[grid_inbound]
    data_in_obs = data_in[grid_inbound][ObsMask[g[:, 0], g[:, 1], g[:, 2]].astype(bool)]

    stl = np.asarray(o3d.io.read_point_cloud(f"{gt_root}/Points/stl/stl{scan:03}_total.ply").points)
    d_d2s = cKDTree(stl).query(data_in_obs)[0]
    plane = scipy.io.loadmat(f"{gt_root}/ObsMask/Plane{scan}.mat")["P"]
    above = (plane.reshape((1, 4)) * np.c_[stl, np.ones(len(stl))]).sum(-1) > 0
    d_s2d = cKDTree(data_in).query(stl[above])[0]
    return d_d2s[d_d2s < max_dist].mean(), d_s2d[d_s2d < max_dist].mean(), keep, len(data_down), len(data_in_obs)


def test_culling_matches_the_script_at_image_borders():
    views = synthetic_views()
    v = views[1]
    H, W = v.mask.shape
    # Points whose pixels cover the image and a 3 px band around it, at 450-550 mm depth.
    rng = np.random.default_rng(0)
    px = np.c_[rng.uniform(-3, W + 2, 30000), rng.uniform(-3, H + 2, 30000), np.ones(30000)]
    cam = (px @ np.linalg.inv(v.K).T) * rng.uniform(450, 550, (30000, 1))
    pts = (cam - v.world_to_cam[:3, 3]) @ v.world_to_cam[:3, :3]
    keep = dtu_eval.cull_vertices(pts, [v], 24.0)
    np.testing.assert_array_equal(keep, script_cull(pts, [v]))
    border = (px[:, 0] <= 0) | (px[:, 0] >= W - 1) | (px[:, 1] <= 0) | (px[:, 1] >= H - 1)
    assert keep[border].all() and not keep[~border].all()


def test_matches_a_transcription_of_the_public_script(tmp_path):
    V, F, N = sphere(radius=15.0, resolution=16)
    # Only the half facing the cameras is observed; the ground cuts the far cap.
    dense = sample_mesh(V, F, 0.5)
    gtmod.write_ground_truth(tmp_path, 77, V, F, np.array([0, 0, -1.0, CENTRE[2] + 10]),
                             observed_points_mm=dense[dense[:, 2] < CENTRE[2]], res_mm=2.0)
    g = gtmod.read_ground_truth(tmp_path)
    rng = np.random.default_rng(5)
    Vd, Fd, _ = sphere(radius=4.0, centre=CENTRE + [0, 30.0, 0], resolution=8)  # culled
    Vf, Ff, _ = sphere(radius=3.0, centre=CENTRE + [0, 0, -26.0], resolution=8)  # kept, not observed
    data_V = np.concatenate([V + (1.0 + rng.normal(scale=0.3, size=(len(V), 1))) * N, Vd, Vf])
    data_F = np.concatenate([F, Fd + len(V), Ff + len(V) + len(Vd)])
    views = synthetic_views()
    for v in views:  # silhouettes of the 15 mm ball, so that some data is culled
        v.mask[:] = ball_mask(v.K, v.world_to_cam, v.mask.shape, radius=15.0)
    m = dtu_eval.evaluate_mesh(data_V, data_F, g, EvaluateConfig.default(), views=views, seed=3, log=None)
    acc, comp, keep, n_down, n_obs = public_script(data_V, data_F, views, tmp_path, 77, seed=3)
    assert m["counts"]["culled_vertices"] == keep.sum() < len(data_V)
    assert m["counts"]["data_downsampled"] == n_down and m["counts"]["data_in_obs"] == n_obs
    assert m["counts"]["data_in_bb"] > 1.3 * n_obs  # the floater and the unobserved half: in the box only
    assert m["accuracy_mm"] == pytest.approx(acc, rel=1e-9) and m["completeness_mm"] == pytest.approx(comp, rel=1e-9)


# --- command line ---------------------------------------------------------------------------


def write_synthetic_scene(root, V, F):
    views = synthetic_views()
    norm_to_world = np.eye(4)
    norm_to_world[:3, :3] *= 1.5 * RADIUS
    norm_to_world[:3, 3] = CENTRE
    dtu.write_scene(
        root,
        images={v.view_id: np.dstack([v.mask] * 3).astype(np.float32) for v in views},
        K={v.view_id: v.K for v in views},
        world_to_cam={v.view_id: v.world_to_cam for v in views},
        norm_to_world=norm_to_world,
        masks={v.view_id: v.mask for v in views},
        meta={"name": "ball", "scan_id": 1002},
    )
    gtmod.write_ground_truth(root / "gt", 1002, V, F, PLANE)


def test_cli_writes_metrics(tmp_path, capsys):
    V, F, N = sphere()
    write_synthetic_scene(tmp_path / "scene", V, F)
    gtmod.write_ply_mesh(tmp_path / "offset.ply", V + 2.0 * N, F)
    out = tmp_path / "res" / "metrics.json"
    rc = main(["evaluate", "--mesh", str(tmp_path / "offset.ply"), "--scene", str(tmp_path / "scene"),
               "--views", "0", "1", "2", "--out", str(out)])
    assert rc == 0
    m = json.loads(out.read_text())
    assert m["accuracy_mm"] == pytest.approx(2.0, rel=0.1) and m["completeness_mm"] == pytest.approx(2.0, rel=0.1)
    assert m["scan_id"] == 1002 and m["config"]["cull_view_ids"] == [0, 1, 2] and m["config"]["max_dist_mm"] == 20.0
    for key in ("data_sampled", "data_downsampled", "data_in_bb", "data_in_obs", "gt_above_plane"):
        assert m["counts"][key] > 0
    assert set(m["timings_s"]) >= {"sample", "downsample", "accuracy", "completeness", "total"}
    assert "[evaluate] accuracy" in capsys.readouterr().out

    # A far-away mesh: exit 0, nulls, a warning.
    gtmod.write_ply_mesh(tmp_path / "far.ply", V + [0, 0, 2000.0], F)
    assert main(["evaluate", "--mesh", str(tmp_path / "far.ply"), "--scene", str(tmp_path / "scene"),
                 "--cull", "none", "--out", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["accuracy_mm"] is None and m["overall_mm"] is None and m["valid"] is False
    assert "metrics undefined" in capsys.readouterr().err


def test_cli_errors_name_the_problem(tmp_path, capsys):
    V, F, _ = sphere(resolution=10)
    write_synthetic_scene(tmp_path / "scene", V, F)
    gtmod.write_ply_points(tmp_path / "points_only.ply", V)
    out = tmp_path / "m.json"
    args = ["--scene", str(tmp_path / "scene"), "--views", "0", "1", "2", "--out", str(out)]
    assert main(["evaluate", "--mesh", str(tmp_path / "points_only.ply"), *args]) == 1
    assert "points_only.ply: has no triangles" in capsys.readouterr().err
    assert main(["evaluate", "--mesh", str(tmp_path / "missing.ply"), *args]) == 1
    assert "missing.ply: file not found" in capsys.readouterr().err
    (tmp_path / "garbage.ply").write_bytes(b"not a mesh")
    assert main(["evaluate", "--mesh", str(tmp_path / "garbage.ply"), *args]) == 1
    assert "garbage.ply: not a PLY file" in capsys.readouterr().err
    (tmp_path / "no_gt").mkdir()
    assert main(["evaluate", "--mesh", str(tmp_path / "points_only.ply"), "--gt", str(tmp_path / "no_gt"), *args]) == 1
    assert "ObsMask" in capsys.readouterr().err
    assert not out.exists()


def upper_half(V, F, N=None):
    """The sphere's triangles whose centroid is above its centre in y (a hemisphere)."""
    keep = V[F].mean(axis=1)[:, 1] > CENTRE[1]
    return V, F[keep]


def test_split_by_reference_separates_the_shared_part():
    from pipeline.evaluation.coverage import split_by_reference

    V, F, _ = sphere()
    ref_V, ref_F = upper_half(V, F)
    parts = split_by_reference(V, F, ref_V, ref_F, within_mm=0.5)
    assert len(parts["shared"][1]) + len(parts["added"][1]) == len(F)
    for Vp, Fp in parts.values():
        assert Fp.max() == len(Vp) - 1  # only the vertices the part uses
    # The reference's own triangles, and those across the cut whose centroid is within 0.5 mm of it.
    shared_y = parts["shared"][0][parts["shared"][1]].mean(axis=1)[:, 1]
    added_y = parts["added"][0][parts["added"][1]].mean(axis=1)[:, 1]
    assert len(ref_F) <= len(shared_y) < len(ref_F) * 1.05
    assert (shared_y > CENTRE[1] - 0.5).all() and (added_y < CENTRE[1]).all()


def test_accuracy_by_reference_scores_each_part_as_a_mesh(ground_truth):
    """A mesh equal to the GT above the reference's cut and 2 mm outside it below: the shared
    part scores ~0, the added part ~2, and the parts' weighted mean is the whole's accuracy."""
    from pipeline.evaluation.coverage import accuracy_by_reference

    V, F, N = sphere()
    below = V[:, 1] < CENTRE[1] - 5.0  # clear of the cut, so no shared triangle moves
    moved = V + 2.0 * N * below[:, None]
    ref_V, ref_F = upper_half(V, F)
    out = accuracy_by_reference(moved, F, ref_V, ref_F, ground_truth, NO_CULL, within_mm=0.5, log=None)
    assert out["shared"]["accuracy_mm"] < 0.1
    assert out["added"]["accuracy_mm"] == pytest.approx(2.0, rel=0.15)
    assert out["shared"]["fraction"] + out["added"]["fraction"] == pytest.approx(1.0)
    assert 0.3 < out["shared"]["fraction"] < 0.7
    whole = dtu_eval.evaluate_mesh(moved, F, ground_truth, NO_CULL, log=None)["accuracy_mm"]
    parts = sum(out[p]["fraction"] * out[p]["accuracy_mm"] for p in ("shared", "added"))
    assert parts == pytest.approx(whole, rel=0.05)

    # A reference covering everything leaves nothing added: NaN, not an error.
    out = accuracy_by_reference(V, F, V, F, ground_truth, NO_CULL, log=None)
    assert out["shared"]["fraction"] == 1.0 and np.isnan(out["added"]["accuracy_mm"])


def test_accuracy_by_reference_rejects_bad_input(ground_truth):
    from pipeline.evaluation.coverage import accuracy_by_reference

    V, F, _ = sphere()
    with pytest.raises(MeshError, match="reference mesh"):
        accuracy_by_reference(V, F, np.zeros((0, 3)), np.zeros((0, 3), int), ground_truth, NO_CULL, log=None)
    with pytest.raises(ValueError, match="within_mm"):
        accuracy_by_reference(V, F, V, F, ground_truth, NO_CULL, within_mm=0.0, log=None)


def test_cli_accuracy_by_mesh(tmp_path, capsys):
    V, F, N = sphere()
    write_synthetic_scene(tmp_path / "scene", V, F)
    gtmod.write_ply_mesh(tmp_path / "mesh.ply", V + 1.0 * N, F)
    gtmod.write_ply_mesh(tmp_path / "ref.ply", *upper_half(V + 1.0 * N, F))
    out = tmp_path / "m.json"
    assert main(["evaluate", "--mesh", str(tmp_path / "mesh.ply"), "--scene", str(tmp_path / "scene"), "--cull", "none",
                 "--accuracy-by-mesh", str(tmp_path / "ref.ply"), "--out", str(out)]) == 0
    m = json.loads(out.read_text())["accuracy_by_reference"]
    assert m["reference"] == str(tmp_path / "ref.ply") and m["within_mm"] == 1.0
    assert m["shared"]["accuracy_mm"] == pytest.approx(1.0, rel=0.15) == m["added"]["accuracy_mm"]
    assert "accuracy by reference coverage" in capsys.readouterr().out
    assert main(["evaluate", "--mesh", str(tmp_path / "mesh.ply"), "--scene", str(tmp_path / "scene"),
                 "--accuracy-by-mesh", str(tmp_path / "ref.ply"), "--within-mm", "-1", "--out", str(out)]) != 0
    assert "--within-mm" in capsys.readouterr().err
