"""TSDF fusion: exact depth of a known scene fuses into a mesh on that surface."""
from __future__ import annotations

import numpy as np
import pytest

from init_scene import distance_to_spheres, make_scene, spheres_world
from pipeline import geometry
from pipeline.meshing import tsdf


@pytest.fixture(scope="module")
def fused():
    scene, gt = make_scene(320, 240)
    voxel, trunc = tsdf.default_sizes_mm(scene.norm_scale_mm)
    mesh = tsdf.fuse_depth_maps(gt, scene.K, scene.world_to_cam, scene.images, voxel, trunc,
                                depth_max_mm=2000.0)
    return scene, gt, mesh, voxel


def test_default_sizes_follow_the_2dgs_settings():
    assert tsdf.default_sizes_mm(250.0) == pytest.approx((1.0, 4.0))


def test_gt_depth_fuses_onto_the_surface(fused):
    scene, _, mesh, voxel = fused
    assert len(mesh.triangles) > 10000
    d = distance_to_spheres(mesh.vertices_mm, scene)
    assert np.median(d) < 0.5 * voxel, (np.median(d), voxel)
    assert d.max() < 2.0 * voxel
    assert mesh.colors is not None and mesh.colors.shape == mesh.vertices_mm.shape


def test_mesh_covers_what_the_cameras_see(fused):
    """Completeness: GT surface points seen by view 0 have a mesh vertex nearby."""
    scene, gt, mesh, voxel = fused
    from scipy.spatial import cKDTree

    pts = geometry.backproject_depth(scene.K[0], scene.world_to_cam[0], gt[0])
    pts = pts[gt[0] > 0][::7]
    dist, _ = cKDTree(mesh.vertices_mm).query(pts)
    assert np.percentile(dist, 95) < 1.5 * voxel


def test_cleaning_drops_small_components(fused):
    scene, _, mesh, _ = fused
    big, small = spheres_world(scene)
    full = tsdf.keep_largest_components(mesh, num_clusters=10)
    one = tsdf.keep_largest_components(mesh, num_clusters=1)
    assert len(one.triangles) < len(full.triangles)
    # The single kept component is the big sphere: every vertex is on it.
    on_big = np.abs(np.linalg.norm(one.vertices_mm - big[0], axis=1) - big[1])
    assert on_big.max() < 2.0
    assert one.triangles.max() < len(one.vertices_mm)
    frac = tsdf.keep_largest_components(mesh, num_clusters=10, min_fraction=0.99)
    assert len(frac.triangles) == len(one.triangles)


def test_bad_depth_is_rejected():
    K = np.eye(3)[None]
    T = np.eye(4)[None]
    with pytest.raises(ValueError, match="non-finite"):
        tsdf.fuse_depth_maps(np.full((1, 4, 4), np.nan), K, T, None, 1.0, 4.0, 100.0)
    with pytest.raises(ValueError, match="no surface"):
        tsdf.fuse_depth_maps(np.zeros((1, 4, 4)), K, T, None, 1.0, 4.0, 100.0)
    with pytest.raises(ValueError, match="voxel_mm < trunc_mm"):
        tsdf.fuse_depth_maps(np.ones((1, 4, 4)), K, T, None, 1.0, 0.5, 100.0)


def test_written_mesh_reads_back(fused, tmp_path):
    import open3d as o3d

    _, _, mesh, _ = fused
    tsdf.write_mesh(tmp_path / "m.ply", mesh)
    m = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    assert len(m.triangles) == len(mesh.triangles)
    assert [p.name for p in tmp_path.iterdir()] == ["m.ply"]


def test_cli_meshes_an_init_folder(tmp_path, capsys):
    import json

    from pipeline.cli import main
    from pipeline.data.dtu import write_scene
    from pipeline.evaluation.gt import read_mesh
    from pipeline.init.io import DepthMap, depth_path, write_depth

    scene, gt = make_scene(200, 150)
    ids = scene.view_ids
    scene_dir = write_scene(tmp_path / "scene", images=dict(zip(ids, scene.images)), K=dict(zip(ids, scene.K)),
                            world_to_cam=dict(zip(ids, scene.world_to_cam)), norm_to_world=scene.norm_to_world,
                            masks=dict(zip(ids, scene.masks)))
    init_dir = tmp_path / "init"
    assert main(["tsdf", "--init-dir", str(init_dir), "--scene", str(scene_dir), "--out", str(tmp_path / "m.ply")]) == 1
    assert "no depth maps" in capsys.readouterr().err
    for i, v in enumerate(ids):
        valid = gt[i] > 0
        write_depth(depth_path(init_dir, v), DepthMap(v, np.where(valid, gt[i], 0.0).astype(np.float32),
                                                     valid.astype(np.float32), valid, scene.K[i], scene.world_to_cam[i]))
    assert main(["tsdf", "--init-dir", str(init_dir), "--scene", str(scene_dir), "--out", str(tmp_path / "m.ply"),
                 "--num-clusters", "2"]) == 0
    facts = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    V, F = read_mesh(tmp_path / "m.ply")
    assert len(F) == facts["triangles_kept"] > 1000
    # At 200x150 a pixel (~1.8 mm) is coarser than a voxel (0.92 mm): a looser bound than above.
    assert np.median(distance_to_spheres(V, scene)) < facts["voxel_mm"]
