"""Synthetic scenes: determinism, layout, camera handling, rendering, ground truth, CLI."""
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import scipy.ndimage

from pipeline import geometry
from pipeline.cli import main as gcgs
from pipeline.data import dtu
from pipeline.evaluation.gt import read_ground_truth, read_mesh
from pipeline.synth import SCENES, Renderer, build_scene, raycast_depth, shapes, table_frame, write_synth_scene
from pipeline.synth.scenes import visible_gt_mesh

W, H = 160, 120


@pytest.fixture(scope="module")
def relief(tmp_path_factory, bundled_scan):
    out = tmp_path_factory.mktemp("synth") / "nested" / "relief"  # parent created on demand
    write_synth_scene("synth_relief", out, seed=3, width=W, height=H, cameras_dir=bundled_scan, log=None)
    return out


@pytest.fixture(scope="module")
def cams(bundled_scan):
    return dtu.load_cameras(bundled_scan)


def scaled_K(cams, view, width, height):
    return geometry.scale_intrinsics(cams.K[view], width / 800, height / 600)  # bundled cameras: 800x600


def test_scene_reads_back_with_all_views(relief):
    scene = dtu.load_scene(relief, view_ids=None)
    assert scene.view_ids == list(range(49))
    assert scene.images.shape == (49, H, W, 3)
    assert scene.scan_id == SCENES["synth_relief"][0]
    meta = json.loads((relief / "scene.json").read_text())
    assert (meta["name"], meta["seed"], meta["source"]) == ("synth_relief", 3, "synthetic")
    # Every view sees the whole object (no mask pixel on the border) and the table around it.
    cover = scene.masks.reshape(49, -1).mean(axis=1)
    assert np.all(cover > 0.03) and np.all(cover < 0.8)
    border = scene.masks[:, [0, -1]].any() or scene.masks[:, :, [0, -1]].any()
    assert not border
    assert np.all(scene.images[~scene.masks].std(axis=0) > 0.02)


def test_deterministic_from_seed(relief, tmp_path, bundled_scan):
    again = write_synth_scene("synth_relief", tmp_path / "a", seed=3, width=W, height=H,
                              cameras_dir=bundled_scan, log=None)
    other = write_synth_scene("synth_relief", tmp_path / "b", seed=4, width=W, height=H,
                              cameras_dir=bundled_scan, log=None)
    for v in ("image/000023.png", "image/000040.png", "mask/023.png", "cameras_sphere.npz"):
        assert (again / v).read_bytes() == (relief / v).read_bytes()
    for v in ("image/000023.png", "image/000040.png"):
        assert (other / v).read_bytes() != (relief / v).read_bytes()
    a, b = read_mesh(again / "gt" / "mesh.ply"), read_mesh(relief / "gt" / "mesh.ply")
    np.testing.assert_array_equal(a[0], b[0])
    # .mat files carry a creation time in their header: compare their contents.
    ga, gb = read_ground_truth(again / "gt"), read_ground_truth(relief / "gt")
    np.testing.assert_array_equal(ga.obs_mask, gb.obs_mask)
    np.testing.assert_array_equal(ga.points_mm, gb.points_mm)


def test_table_frame_matches_the_dtu_camera_layout(cams):
    """Up is level with the cameras (DTU keeps them unrolled) and the sparse input views
    look down at the table at DTU's ~20-35 degrees, not from overhead."""
    T = table_frame(cams)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)
    up, ground = T[:3, 2], T[:3, 3]
    for v in cams.ids:
        assert abs(cams.world_to_cam[v][0, :3] @ up) < np.sin(np.radians(6))  # camera roll
    centres = {v: geometry.camera_center(cams.world_to_cam[v]) for v in cams.ids}
    assert all((c - ground) @ up > 100 for c in centres.values())  # every camera above the table
    obj = ground + 70 * up  # mid-height of the objects
    for v in (23, 24, 33):
        d = centres[v] - obj
        assert 15 < np.degrees(np.arcsin(d @ up / np.linalg.norm(d))) < 40


def test_table_frame_rejects_unlevelled_cameras(cams):
    rng = np.random.default_rng(0)
    w2c = {}
    for v in cams.ids:  # random orientations: no common horizontal plane
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        T = np.eye(4)
        T[:3, :3] = q * np.sign(np.linalg.det(q))
        T[:3, 3] = [0, 0, 600]
        w2c[v] = T
    bad = dtu.DTUCameras(K=cams.K, world_to_cam=w2c, norm_to_world=cams.norm_to_world, path=cams.path)
    with pytest.raises(ValueError, match="cameras_sphere.npz: the cameras' x axes"):
        table_frame(bad)


def test_depth_reprojects_consistently_between_views(relief):
    """Back-project view 23's GT depth and check it against view 24's own depth map."""
    scene = dtu.load_scene(relief, view_ids=[23, 24])
    V, F = read_mesh(relief / "gt" / "mesh.ply")
    d23 = raycast_depth(V, F, scene.K[0], scene.world_to_cam[0], W, H)
    d24 = raycast_depth(V, F, scene.K[1], scene.world_to_cam[1], W, H)
    pts = geometry.backproject_depth(scene.K[0], scene.world_to_cam[0], d23)[scene.masks[0]]
    px, z = geometry.project(scene.K[1], scene.world_to_cam[1], pts)
    ij = np.rint(px).astype(int)
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
    other = d24[ij[ok, 1], ij[ok, 0]]
    visible = np.abs(other - z[ok]) < 2.0  # mm; occluded points differ by far more
    assert visible.mean() > 0.7
    # Rounding moves the lookup by <= 0.5 px (~1 mm at this size on the slanted sphere).
    assert np.median(np.abs(other - z[ok])[visible]) < 0.5


def test_masks_are_object_hits_and_depths_match_the_mesh(relief, bundled_scan, cams):
    syn = build_scene("synth_relief", 3, cams)
    renderer = Renderer(syn)
    hits = renderer.cast(scaled_K(cams, 23, W, H), cams.world_to_cam[23], W, H)
    mask = dtu.load_masks(relief, [23])[23]
    np.testing.assert_array_equal(mask, renderer.object_mask(hits))
    # The renderer's depth (local frame) equals raycast_depth of the world-frame GT mesh.
    V, F = read_mesh(relief / "gt" / "mesh.ply")
    d = raycast_depth(V, F, scaled_K(cams, 23, W, H), cams.world_to_cam[23], W, H)
    np.testing.assert_allclose(d[mask], hits["depth"][mask], atol=1e-3)
    # Object depth is in DTU range (the cameras are ~640-690 mm from the sphere centre).
    assert 450 < hits["depth"][mask].min() < hits["depth"][mask].max() < 800
    assert np.all(hits["depth"][~hits["hit"]] == 0) and np.all(hits["depth"][hits["hit"]] > 0)  # 0: no depth


def test_views_are_photo_consistent(cams):
    """Solid texture + light fixed in the world: a surface point has the same colour in
    every view, so warping view 24 into view 23 through the true depth matches, and
    through a depth 3 mm off does not."""
    w, h = 400, 300
    renderer = Renderer(build_scene("synth_relief", 0, cams))
    K = {v: scaled_K(cams, v, w, h) for v in (23, 24)}
    hits = {v: renderer.cast(K[v], cams.world_to_cam[v], w, h) for v in (23, 24)}
    img = {v: renderer.shade(hits[v]) for v in (23, 24)}
    mask = renderer.object_mask(hits[23])

    def median_error(offset_mm):
        depth = hits[23]["depth"] + offset_mm
        pts = geometry.backproject_depth(K[23], cams.world_to_cam[23], depth)[mask]
        px, z = geometry.project(K[24], cams.world_to_cam[24], pts)
        ij = np.rint(px).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        ok[ok] = np.abs(hits[24]["depth"][ij[ok, 1], ij[ok, 0]] - z[ok]) < 4.0  # visible in view 24
        warped = np.stack([scipy.ndimage.map_coordinates(img[24][..., c], [px[ok, 1], px[ok, 0]], order=1)
                           for c in range(3)], axis=1)
        return np.median(np.abs(warped - img[23][mask][ok]).max(axis=1))

    exact, off = median_error(0.0), median_error(3.0)
    assert exact < 0.03
    assert off > 2 * exact


def test_silhouettes_are_antialiased(cams):
    """shade() is closer to a 4x4 box-filtered render than one sample per pixel is."""
    renderer = Renderer(build_scene("synth_thin", 0, cams))
    K = scaled_K(cams, 23, W, H)
    hits = renderer.cast(K, cams.world_to_cam[23], W, H)
    img = renderer.shade(hits)
    centre = renderer._shade_samples(hits["_rays"], hits["_trace"]).reshape(H, W, 3)
    fine = renderer.shade(renderer.cast(geometry.scale_intrinsics(K, 4, 4), cams.world_to_cam[23], 4 * W, 4 * H))
    ref = fine.reshape(H, 4, W, 4, 3).mean(axis=(1, 3))
    assert np.abs(img - ref).mean() < 0.6 * np.abs(centre - ref).mean()


def test_ground_truth_files_are_consistent(relief, cams):
    gt = read_ground_truth(relief / "gt")
    V, F = read_mesh(relief / "gt" / "mesh.ply")
    assert gt.scan_id == SCENES["synth_relief"][0]
    # GT points lie on the GT mesh.
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(V.astype(np.float32), F.astype(np.uint32))
    sample = gt.points_mm[:: max(1, len(gt.points_mm) // 20000)]
    dist = rc.compute_distance(o3d.core.Tensor(sample.astype(np.float32))).numpy()
    assert dist.max() < 0.01
    # The evaluation plane separates the object (above) from the table disk (below).
    syn = build_scene("synth_relief", 3, cams)
    local_z = syn.to_local(gt.points_mm)[:, 2]
    above = gt.above_plane(gt.points_mm)
    clear = np.abs(local_z - 1.0) > 1e-6  # the plane is 1 mm above the table
    np.testing.assert_array_equal(above[clear], local_z[clear] > 1.0)
    assert 0.2 < above.mean() < 0.95
    # The ObsMask holds every surface point a camera sees, not the inside of the sphere.
    scene = dtu.load_scene(relief, view_ids=[23, 40])
    for k in range(2):
        d = raycast_depth(V, F, scene.K[k], scene.world_to_cam[k], W, H)
        seen = geometry.backproject_depth(scene.K[k], scene.world_to_cam[k], d)[d > 0]
        idx = gt.voxel_index(seen)
        assert gt.obs_mask[idx[:, 0], idx[:, 1], idx[:, 2]].all()
    centre = gt.voxel_index(syn.to_world(np.array([[0.0, 0.0, 70.0]])))[0]  # 85 mm below the surface
    assert np.all(centre >= 0) and np.all(centre < gt.obs_mask.shape)
    assert not gt.obs_mask[tuple(centre)]


@pytest.mark.parametrize("name", list(SCENES))
def test_parts_are_outward_and_finely_meshed(name):
    """Visibility culling relies on outward normals and small cells."""
    for part in SCENES[name][1](0):
        a, b, c = (part.vertices[part.triangles[:, k]] for k in range(3))
        assert np.einsum("ij,ij->", a, np.cross(b, c)) / 6 > 0  # signed volume: normals point out
        longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1)])
        assert longest < 2.5 * shapes.CELL_MM  # cell diagonals: up to ~1.5 cells


def test_ground_truth_is_the_seen_surface_only(cams):
    """The plinth top under the dome and the dome inside the plinth are never seen: they
    must not be ground truth, while the dome's top and the plinth's rim are kept."""
    syn = build_scene("synth_textureless", 0, cams)
    V, F = visible_gt_mesh(syn, Renderer(syn), cams, (800, 600))
    full_V, full_F = syn.gt_mesh_local()
    assert 0.2 * len(full_F) < len(F) < 0.8 * len(full_F)
    centroids = V[F].mean(axis=1)
    dome = syn.parts[0].vertices
    semi = np.array([dome[:, 0].max(), dome[:, 1].max(), (dome[:, 2].max() - 65.0)])  # ellipsoid centred at z = 65
    r = np.linalg.norm((centroids - [0.0, 0.0, 65.0]) / semi, axis=1)
    assert not np.any(r < 0.97)  # nothing inside the dome
    plinth_r = syn.parts[1].vertices[:, 0].max()
    inside_plinth = (np.hypot(centroids[:, 0] / plinth_r, centroids[:, 1] / syn.parts[1].vertices[:, 1].max()) < 0.97) \
        & (centroids[:, 2] < 15.0) & (centroids[:, 2] > 1.0)
    assert not np.any(inside_plinth)
    top = (centroids[:, 2] > 65.0 + 0.8 * semi[2])
    full_c = full_V[full_F].mean(axis=1)
    assert top.sum() == np.sum(full_c[: len(syn.parts[0].triangles), 2] > 65.0 + 0.8 * semi[2])


def test_cli_list_and_bad_arguments(capsys, tmp_path, bundled_scan):
    assert gcgs(["synth", "--list"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in SCENES)
    assert gcgs(["synth", "nope", "--out", str(tmp_path / "x")]) == 1
    assert "unknown synthetic scene 'nope'" in capsys.readouterr().err
    assert gcgs(["synth", "synth_thin", "--out", str(tmp_path / "x"), "--width", "0"]) == 1
    assert "image size must be positive" in capsys.readouterr().err
    assert gcgs(["synth", "synth_thin", "--out", str(tmp_path / "x"), "--cameras", str(tmp_path / "none")]) == 1
    assert str(tmp_path / "none") in capsys.readouterr().err
    assert gcgs(["synth", "synth_thin"]) == 1
    assert "--out" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_the_3_view_limit_is_the_gt_the_input_views_see(relief, tmp_path, bundled_scan):
    """The limit mesh keeps exactly the GT triangles the given views see: all 49 views give the
    whole GT mesh back, three give a strict subset lying on it, and more views never see less."""
    from pipeline.config.data import DataConfig
    from pipeline.config.evaluate import EvaluateConfig
    from pipeline.config.mesh import MeshConfig
    from pipeline.data.prepare import prepare_scene
    from pipeline.data.scene import SceneError
    from pipeline.evaluation import gt
    from pipeline.synth.limit import limit_mesh, mesh_area_mm2
    from pipeline.runs.limit import run_limit
    from pipeline.raycast import distance_to_mesh

    V_gt, F_gt = gt.read_mesh(relief / "gt" / "mesh.ply")
    V_all, F_all = limit_mesh(relief, dtu.load_cameras(relief).ids)
    assert len(F_all) == len(F_gt)
    np.testing.assert_allclose(mesh_area_mm2(V_all, F_all), mesh_area_mm2(V_gt, F_gt), rtol=1e-5)
    V3, F3 = limit_mesh(relief, [23, 24, 33])
    V4, F4 = limit_mesh(relief, [23, 24, 33, 0])
    assert 0 < mesh_area_mm2(V3, F3) < mesh_area_mm2(V4, F4) < mesh_area_mm2(V_gt, F_gt)
    assert distance_to_mesh(V3, V_gt, F_gt).max() < 1e-3
    scene = tmp_path / "scene"
    prepare_scene(relief, scene, DataConfig(views=[23, 24, 33], width=W, height=H))
    # conf/'s mesh settings with those this test was written with (2DGS's voxel 0.004, no init
    # depth, no hole closing; conf/ has 0.003, 0.002, 0.1).
    mesh = MeshConfig.default(voxel_norm=0.004, init_depth_rel_tol=0.0, fill_holes_norm=0.0)
    report = run_limit(relief, scene, tmp_path / "limit", EvaluateConfig.default(), mesh, [23, 24, 33])
    c = report["chamfer"]
    assert c["accuracy_mm"] < 0.2 < c["completeness_mm"] and 0 < report["gt_area_seen_fraction"] < 1
    # What the limit leaves uncovered is what no input view sees (docs/evaluation.md).
    by_gt = c["completeness_by_views_seen"]
    assert by_gt["2+"]["completeness_mm"] < 0.2 < by_gt["0"]["completeness_mm"]
    assert c["accuracy_by_views_seen"]["2+"]["accuracy_mm"] < 0.2
    assert gt.read_mesh(tmp_path / "limit" / "mesh.ply")[1].shape == F3.shape
    # The meshing fed exact depth: on the GT (within the TSDF's voxel), never more complete
    # than what the views see.
    e = report["exact_depth"]
    V_e, F_e = gt.read_mesh(tmp_path / "limit" / "exact_depth_mesh.ply")
    voxel_mm = mesh.sizes_mm(float(dtu.load_cameras(relief).norm_to_world[0, 0]))[0]
    assert len(F_e) > 0 and np.median(distance_to_mesh(V_e, V_gt, F_gt)) < 0.4 * voxel_mm
    assert e["accuracy_mm"] < 0.5 * voxel_mm and e["completeness_mm"] > c["completeness_mm"] - 0.05
    with pytest.raises(SceneError, match="not a synthetic scene"):
        limit_mesh(bundled_scan, [23, 24, 33])


# --- The same bytes on any x86-64 machine (issue 18) -------------------------------------------

HASHES = Path(__file__).with_name("synth_hashes.json")  # regenerate: GCGS_WRITE_SYNTH_HASHES=1 pytest -k committed


class _CasterWithOtherFloats:
    """Open3D's ray caster whose float outputs come out as another CPU's code path could
    give them: hit distances a few float32 ulps off, barycentrics and normals perturbed."""

    def __init__(self, caster):
        self._caster = caster

    def __getattr__(self, name):
        return getattr(self._caster, name)

    def cast_rays(self, rays):
        ans = self._caster.cast_rays(rays)
        out = {k: ans[k].numpy().copy() for k in ("t_hit", "geometry_ids", "primitive_ids", "primitive_uvs",
                                                   "primitive_normals")}
        out["t_hit"] *= np.float32(1 + 3e-7)
        out["primitive_uvs"] += np.float32(1e-6)
        out["primitive_normals"] *= np.float32(1 + 1e-6)
        return {k: o3d.core.Tensor(v) for k, v in out.items()}


def test_render_does_not_depend_on_the_ray_casters_float_path(cams):
    scene = build_scene("synth_thin", 0, cams)
    plain, other = Renderer(scene), Renderer(scene)
    other.raycaster = _CasterWithOtherFloats(other.raycaster)
    for v in (23, 33):
        K = scaled_K(cams, v, W, H)
        a, b = plain.cast(K, cams.world_to_cam[v], W, H), other.cast(K, cams.world_to_cam[v], W, H)
        np.testing.assert_array_equal(a["depth"], b["depth"])
        np.testing.assert_array_equal(plain.shade(a), other.shade(b))


def test_snap_merges_last_bit_differences_of_each_columns_scale_and_keeps_32_bits():
    from pipeline.synth.render import snap

    rng = np.random.default_rng(0)
    # columns of very different scales, each holding entries far below its scale
    x = rng.normal(size=(1000, 3)) * 10.0 ** rng.integers(-4, 4, (1000, 3)) * np.array([1e-3, 1.0, 1e3])
    s = snap(x)
    scale = np.abs(x).max(axis=0)
    assert np.all(np.abs(s - x) <= scale * 2.0**-32)
    assert np.any(s != x)
    for ulps in (1, -1, 3):
        # an error of a few ulps of the column's scale, as LAPACK and BLAS make, on every entry
        noise = ulps * np.spacing(scale) * rng.choice([-1.0, 1.0], size=x.shape)
        # equal unless an entry lies within those ulps of a rounding boundary (odds ~1e-8 here)
        np.testing.assert_array_equal(snap(x + noise), s)
    assert snap(0.0) == 0.0 and snap(s).tolist() == s.tolist()
    assert snap(np.zeros(3)).tolist() == [0.0, 0.0, 0.0]
    v = np.array([700.0, -3e-9, 0.25])  # a vector: one scale for all its entries
    np.testing.assert_array_equal(snap(v + np.spacing(700.0)), snap(v))


def test_snapped_cameras_ignore_decomposition_noise(bundled_scan):
    """The world matrices perturbed by a few ulps (what another CPU's LAPACK does to the
    decomposition) give the same snapped intrinsics and poses: the skew, ~1e-4 beside a
    focal length of ~1e3, is noise far above its own last bit."""
    from pipeline import geometry
    from pipeline.data import dtu
    from pipeline.synth.render import snap

    cams = dtu.load_cameras(bundled_scan)
    data = np.load(cams.path)
    rng = np.random.default_rng(1)
    for v in cams.ids:
        P = np.asarray(data[f"world_mat_{v}"], np.float64)
        K, w2c = geometry.decompose_projection(P * (1.0 + rng.integers(-4, 5, P.shape) * 2.0**-52))
        Ks = geometry.scale_intrinsics(K, 0.05, 0.05)
        np.testing.assert_array_equal(snap(K), snap(cams.K[v]), err_msg=f"view {v}")
        np.testing.assert_array_equal(snap(Ks), snap(geometry.scale_intrinsics(cams.K[v], 0.05, 0.05)), err_msg=f"view {v}")
        np.testing.assert_array_equal(snap(w2c), snap(cams.world_to_cam[v]), err_msg=f"view {v}")


@pytest.mark.parametrize("name", ["synth_textureless", "synth_relief", "synth_thin"])
def test_synthetic_scenes_have_the_committed_bytes(name, tmp_path, bundled_scan):
    """Every file of each scene (images, masks, cameras, ground truth) has the SHA-256 the
    repository holds: what this machine renders is what any x86-64 machine renders."""
    import hashlib
    import os

    out = write_synth_scene(name, tmp_path / name, seed=0, width=80, height=60, cameras_dir=bundled_scan, log=None)
    got = {str(p.relative_to(out)): hashlib.sha256(p.read_bytes()).hexdigest()
           for p in sorted(out.rglob("*")) if p.is_file() and p.name != "scene.json"}
    committed = json.loads(HASHES.read_text()) if HASHES.is_file() else {}
    if os.environ.get("GCGS_WRITE_SYNTH_HASHES"):
        committed[name] = got
        HASHES.write_text(json.dumps(committed, indent=1, sort_keys=True) + "\n")
    assert got == committed[name]
