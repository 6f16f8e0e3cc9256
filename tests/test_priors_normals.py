"""Normal priors: the depth-based estimator against an analytic sphere, and the DSINE
sign convention through a real ONNX model that emits analytic normals."""
from __future__ import annotations

import numpy as np
import pytest

from onnx_helpers import SPHERE_CENTRE_CAM, SPHERE_RADIUS, export_fake_dsine
from pipeline.config.priors import PriorsConfig
from pipeline.onnx_models import DSINE_CONTRACT, load_onnx
from pipeline.priors.normals import NormalError, dsine_inputs, dsine_normals, normals_from_depth

W, H = 100, 75  # not multiples of 32: exercises the padding
K = np.array([[120.0, 0.0, 51.3], [0.0, 118.0, 36.8], [0.0, 0.0, 1.0]])
# Closer-up camera for the depth-based estimator: the sphere spans ~65 px, 2.4 mm/px.
K_NEAR = np.array([[250.0, 0.0, 51.3], [0.0, 245.0, 36.8], [0.0, 0.0, 1.0]])
BACKGROUND_Z = 900.0
UNSMOOTHED = PriorsConfig.default(normal_smooth_sigma_px=0)


def sphere_gt(K=K):
    """Depth (mm) of a sphere in front of a plane z = BACKGROUND_Z, and the sphere's
    outward normals (facing the camera on the visible side), camera frame."""
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    rays = np.stack([xs, ys, np.ones_like(xs)], -1) @ np.linalg.inv(K).T  # z = 1
    c = np.array(SPHERE_CENTRE_CAM)
    a = np.sum(rays * rays, -1)
    b = rays @ c
    disc = b * b - a * (c @ c - SPHERE_RADIUS**2)
    hit = disc > 0
    t = (b - np.sqrt(np.maximum(disc, 0))) / a  # camera z of the near intersection
    depth = np.where(hit, t, BACKGROUND_Z)
    n = (rays * t[..., None] - c) / SPHERE_RADIUS
    return depth, n, hit, rays


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def test_depth_normals_match_analytic_sphere():
    depth, n_gt, hit, rays = sphere_gt(K_NEAR)
    n, ok = normals_from_depth(depth, np.ones_like(hit), K_NEAR, UNSMOOTHED)
    interior = hit & ok
    assert interior.sum() > 0.85 * hit.sum()  # only the rim is lost
    err = angle_deg(n[interior], n_gt[interior])
    # Central differences over +-2 px of a curved surface: small bias, largest at the rim.
    assert np.median(err) < 0.3 and np.percentile(err, 99) < 5.0
    # Every valid normal faces the camera; silhouette pixels (depth jumps) are invalid.
    assert np.all(np.sum(n[ok] * rays[ok], -1) < 0)
    edge = hit & ~np.roll(hit, 2, axis=1)
    assert not ok[edge].any()
    # The background plane z = const has normal (0, 0, -1).
    bg = ok & ~hit
    assert bg.sum() > 100 and np.all(angle_deg(n[bg], np.array([0.0, 0.0, -1.0])) < 1e-3)


def test_smoothing_reduces_noise_and_invalid_pixels_are_excluded():
    depth, n_gt, hit, _ = sphere_gt(K_NEAR)
    noisy = depth + np.random.default_rng(0).normal(0, 1.0, depth.shape)  # 1 mm depth noise
    valid = np.ones_like(hit)
    valid[30:34, 40:44] = False  # a hole in the depth map
    raw, ok_raw = normals_from_depth(noisy, valid, K_NEAR, UNSMOOTHED)
    smooth, ok = normals_from_depth(noisy, valid, K_NEAR, PriorsConfig.default(normal_smooth_sigma_px=1.5, normal_smooth_sigma_mm=3.0))
    m = hit & ok & ok_raw
    assert m.sum() > 0.8 * hit.sum()
    assert np.median(angle_deg(smooth[m], n_gt[m])) < 0.7 * np.median(angle_deg(raw[m], n_gt[m]))
    # The hole and the pixels whose +-2 px neighbours fall in it are invalid.
    assert not ok[30:34, 38:46].any() and not ok[28:36, 40:44].any()
    assert np.all(smooth[~ok] == 0)
    with pytest.raises(NormalError, match="no valid depth"):
        normals_from_depth(depth, np.zeros_like(hit), K, PriorsConfig.default())


def test_dsine_padding_and_sign_convention(tmp_path):
    """The fake model emits the sphere's normals in DSINE's convention (away from the
    camera), computed from the padded intrinsics it is given; after cropping and our
    conversion they must equal the analytic normals facing the camera."""
    model = load_onnx(export_fake_dsine(tmp_path / "dsine.onnx"), DSINE_CONTRACT)
    img = np.random.default_rng(0).uniform(size=(H, W, 3)).astype(np.float32)
    inputs, (left, r, t, b) = dsine_inputs(img, K)
    assert inputs["image"].shape == (1, 3, 96, 128) and (left, r, t, b) == (14, 14, 10, 11)
    n, ok = dsine_normals(model, img, K)
    depth, n_gt, hit, rays = sphere_gt()
    assert ok[hit].all()
    assert np.max(angle_deg(n[hit], n_gt[hit])) < 0.05
    assert np.all(np.sum(n[ok] * rays[ok], -1) < 0)
    # The same convention as the depth-based normals of the same geometry.
    n_d, ok_d = normals_from_depth(depth, np.ones_like(hit), K, UNSMOOTHED)
    m = hit & ok_d
    assert np.median(angle_deg(n[m], n_d[m])) < 1.0


def test_rendered_mesh_normals_share_the_convention():
    """Ray-cast normals of a sphere mesh (what the synthetic ground truth gives) face the
    camera like the analytic ones."""
    import open3d as o3d

    from pipeline.raycast import MeshCaster

    mesh = o3d.geometry.TriangleMesh.create_sphere(SPHERE_RADIUS, resolution=80)
    mesh.translate(SPHERE_CENTRE_CAM)
    hits = MeshCaster(np.asarray(mesh.vertices), np.asarray(mesh.triangles)).cast(K, np.eye(4), H, W)
    depth, n_gt, hit, _ = sphere_gt()
    m = hit & (hits.depth_mm > 0)
    assert m.sum() > 0.9 * hit.sum()
    assert np.median(angle_deg(hits.normal_cam[m], n_gt[m])) < 3.0
    assert np.median(np.abs(hits.depth_mm[m] - depth[m])) < 0.5
