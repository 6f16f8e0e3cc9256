"""The bounding region for depth fused without masks (pipeline.meshing.region): a sphere in
a table seen by the scan24 cameras, ray-cast exactly; the table is found and
cut, the object kept, and nothing changes where masks already cut the depth."""
from __future__ import annotations

import numpy as np
import pytest

from init_scene import make_scene, ray_cast
from pipeline import geometry
from pipeline.config.mesh import MeshConfig
from pipeline.errors import ConfigError
from pipeline.meshing import region as bounding, tsdf


def mesh_config(**changes) -> MeshConfig:
    """conf/'s mesh settings with those these tests were written with where conf/ has others
    (2DGS's voxel 0.004, no init depth, no hole closing)."""
    return MeshConfig.default(voxel_norm=0.004, init_depth_rel_tol=0.0, fill_holes_norm=0.0, **changes)


def _table_scene(width=160, height=120):
    """Depth maps (mm) of a sphere sunk past its equator into an unbounded plane (a cap:
    its base, where it meets the plane, is in view of the cameras above), and (plane,
    sphere)."""
    scene, _ = make_scene(width, height)
    c, r = scene.norm_to_world[:3, 3], scene.norm_scale_mm
    up = np.mean([geometry.camera_center(T) for T in scene.world_to_cam], 0) - c
    up /= np.linalg.norm(up)
    radius = 0.3 * r
    centre = c
    plane = np.append(up, -up @ (c + 0.3 * radius * up))
    depths = []
    for K, T in zip(scene.K, scene.world_to_cam):
        z_sphere, _ = ray_cast(K, T, height, width, [(centre, radius)])
        rays_cam = geometry.pixel_rays(K, shape=(height, width))
        R, t = T[:3, :3], T[:3, 3]
        cam_c = geometry.camera_center(T)
        dirs = rays_cam @ R  # world direction of each ray with camera z = 1
        denom = dirs @ plane[:3]
        with np.errstate(divide="ignore", invalid="ignore"):
            z_plane = -(cam_c @ plane[:3] + plane[3]) / denom
        z_plane = np.where(np.isfinite(z_plane) & (z_plane > 0), z_plane, np.inf)
        z = np.where(z_sphere > 0, np.minimum(z_sphere, z_plane), z_plane)
        depths.append(np.where(np.isfinite(z), z, 0.0))
    return scene, np.stack(depths), plane, (centre, radius)


@pytest.fixture(scope="module")
def table():
    return _table_scene()


def test_ransac_recovers_a_noisy_plane_among_outliers():
    rng = np.random.default_rng(1)
    n = np.array([0.2, -0.3, 0.9])
    n /= np.linalg.norm(n)
    u = np.cross(n, [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    on = rng.uniform(-100, 100, (3000, 1)) * u + rng.uniform(-100, 100, (3000, 1)) * v + 5.0 * n
    on += rng.normal(0, 0.1, (3000, 1)) * n
    off = rng.uniform(-100, 100, (2000, 3))
    plane, inliers = bounding.fit_plane_ransac(np.concatenate([on, off]), inlier_mm=0.5)
    sign = np.sign(plane[:3] @ n)
    assert np.allclose(sign * plane[:3], n, atol=2e-3)
    assert sign * plane[3] == pytest.approx(-5.0, abs=0.05)
    assert inliers[:3000].mean() > 0.99 and inliers[3000:].mean() < 0.02


def test_table_is_found_above_which_the_cameras_are(table):
    scene, depths, plane, _ = table
    voxel, _ = mesh_config().sizes_mm(scene.norm_scale_mm)
    region, facts = bounding.region_for_depths(depths, scene.K, scene.world_to_cam, scene.norm_to_world, voxel,
                                               0.15, 2.0)
    assert region.plane is not None, facts
    assert np.allclose(region.plane[:3], plane[:3], atol=1e-3)
    assert region.plane[3] == pytest.approx(plane[3], abs=0.1)
    assert facts["cameras_above"]


def test_cut_keeps_the_object_and_drops_the_table_like_a_per_pixel_reference(table):
    scene, depths, plane, (centre, radius) = table
    cfg = mesh_config()
    cut, region, facts = bounding.cut_to_region(depths, scene.K, scene.world_to_cam, scene.norm_to_world, cfg,
                                                masked=False)
    assert region is not None and facts["region"]["depth_pixels_cut"] > 0
    margin = cfg.region_plane_margin_norm * scene.norm_scale_mm
    # Reference: one pixel at a time.
    for i, (K, T) in enumerate(zip(scene.K, scene.world_to_cam)):
        inv = np.linalg.inv(T)
        for v, u in zip(*np.nonzero(depths[i] > 0)):
            p = inv[:3, :3] @ (np.linalg.inv(K) @ np.array([u, v, 1.0]) * depths[i, v, u]) + inv[:3, 3]
            keep = (np.linalg.norm(p - region.centre_mm) <= region.radius_mm
                    and p @ region.plane[:3] + region.plane[3] > margin)
            assert (cut[i, v, u] > 0) == keep
    # What stays is the whole sphere above the margin (its base fixes the footprint); the
    # table is gone.
    assert region.footprint is not None and facts["region"]["footprint_points"] > 100
    pts = bounding.depth_points_mm(cut, scene.K, scene.world_to_cam)
    assert np.abs(np.linalg.norm(pts - centre, axis=1) - radius).max() < 1e-6 * radius + 1e-6
    assert ((pts @ plane[:3] + plane[3]) > margin).all()
    everything = bounding.depth_points_mm(depths, scene.K, scene.world_to_cam)
    on_sphere = np.abs(np.linalg.norm(everything - centre, axis=1) - radius) < 1e-6 * radius + 1e-6
    assert len(pts) == (on_sphere & (everything @ plane[:3] + plane[3] > margin)).sum()


def test_footprint_cuts_floaters_beside_the_object_not_above_it(table):
    scene, depths, plane, (centre, radius) = table
    cut, region, _ = bounding.cut_to_region(depths, scene.K, scene.world_to_cam, scene.norm_to_world, mesh_config(),
                                            masked=False)
    up = plane[:3]
    side = np.cross(up, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    above = centre + 1.5 * radius * up
    beside = centre + 0.5 * radius * up + 3.0 * radius * side
    assert region.contains(np.stack([above, beside])).tolist() == [True, False]


def test_fused_without_the_region_the_table_is_meshed_and_with_it_not(table):
    scene, depths, _, (centre, radius) = table
    cfg = mesh_config()
    voxel, trunc = cfg.sizes_mm(scene.norm_scale_mm)
    cut, region, _ = bounding.cut_to_region(depths, scene.K, scene.world_to_cam, scene.norm_to_world, cfg, False)
    kept = []
    for d in (depths, cut):
        mesh = tsdf.fuse_depth_maps(d, scene.K, scene.world_to_cam, None, voxel, trunc, depth_max_mm=2000.0)
        if d is cut:
            mesh.triangles = bounding.crop_mesh_vertices(mesh.vertices_mm, mesh.triangles, region)
        used = np.unique(mesh.triangles)
        kept.append(np.abs(np.linalg.norm(mesh.vertices_mm[used] - centre, axis=1) - radius))
    assert (kept[0] > 5 * voxel).mean() > 0.3  # the table
    assert (kept[1] > 2 * voxel).mean() < 0.01


def test_masked_depth_is_left_alone_unless_asked(table):
    scene, depths, _, _ = table
    same, region, facts = bounding.cut_to_region(depths, scene.K, scene.world_to_cam, scene.norm_to_world,
                                                 mesh_config(), masked=True)
    assert region is None and same is depths and facts == {"region": None}
    off, region, _ = bounding.cut_to_region(depths, scene.K, scene.world_to_cam, scene.norm_to_world,
                                            mesh_config(region="off"), masked=False)
    assert region is None and off is depths
    on, region, _ = bounding.cut_to_region(depths, scene.K, scene.world_to_cam, scene.norm_to_world,
                                           mesh_config(region="on"), masked=True)
    assert region is not None and (on > 0).sum() < (depths > 0).sum()


def test_no_plane_without_a_table_and_none_between_the_cameras():
    scene, depths = make_scene(160, 120)
    voxel, _ = mesh_config().sizes_mm(scene.norm_scale_mm)
    region, facts = bounding.region_for_depths(depths, scene.K, scene.world_to_cam, scene.norm_to_world, voxel,
                                               0.15, 2.0)
    assert region.plane is None and facts["plane_share"] < 0.15
    # A plane with cameras on both of its sides is no table.
    pts = np.random.default_rng(0).uniform(-50, 50, (500, 3)) * [1, 1, 0]
    plane, facts = bounding.support_plane(pts, np.array([[0, 0, 100.0], [0, 0, -100.0]]), 1.0, 0.15)
    assert plane is None and not facts["cameras_above"]


def test_bad_region_settings_are_refused():
    with pytest.raises(ConfigError, match="mesh.region"):
        MeshConfig.default(region="sphere")
    with pytest.raises(ConfigError, match="region_plane_share"):
        MeshConfig.default(region_plane_share=0.0)
