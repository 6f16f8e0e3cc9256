import numpy as np
import pytest

from pipeline import geometry


def random_camera(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])
    K = np.array([[2892.3, -2.5e-4, 823.2], [0, 2883.2, 619.1], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = rng.normal(size=3) * 100
    return K, T


@pytest.mark.parametrize("seed", range(5))
def test_decompose_recovers_K_R_t_and_reprojects(seed):
    rng = np.random.default_rng(seed)
    K, T = random_camera(rng)
    P = geometry.compose_projection(K, T) * rng.uniform(0.1, 10)  # projections are up to scale
    K2, T2 = geometry.decompose_projection(P)
    np.testing.assert_allclose(K2, K, rtol=1e-9, atol=1e-7)
    np.testing.assert_allclose(T2, T, atol=1e-8)
    assert np.linalg.det(T2[:3, :3]) == pytest.approx(1.0)
    pts = rng.normal(size=(50, 3)) * 50 + geometry.camera_center(T) + T[2, :3] * 600  # in front
    uvw = np.c_[pts, np.ones(50)] @ P[:3].T
    px, z = geometry.project(K2, T2, pts)
    np.testing.assert_allclose(px, uvw[:, :2] / uvw[:, 2:], rtol=1e-9)
    assert np.all(z > 0)


def test_decompose_negative_scale_gives_proper_rotation():
    K, T = random_camera(np.random.default_rng(7))
    K2, T2 = geometry.decompose_projection(-geometry.compose_projection(K, T))
    np.testing.assert_allclose(T2, T, atol=1e-8)


@pytest.mark.parametrize("bad", [np.full((3, 4), np.nan), np.zeros((3, 4)), np.ones((2, 4))])
def test_decompose_rejects_bad_matrices(bad):
    with pytest.raises(geometry.CameraError):
        geometry.decompose_projection(bad)


def test_scale_intrinsics_integer_centre_convention():
    """Downscaling by 2 with area averaging: the 2x2 block of old pixels (2i..2i+1, 2j..2j+1),
    whose centre is at old coordinate (2j+0.5, 2i+0.5), becomes new pixel (i, j)."""
    import cv2

    K = np.array([[100.0, 0, 31.5], [0, 100.0, 23.5], [0, 0, 1]])
    K2 = geometry.scale_intrinsics(K, 0.5, 0.5)
    img = np.zeros((48, 64), np.float32)
    img[20:22, 30:32] = 1.0  # 2x2 block centred at old (30.5, 20.5)
    small = cv2.resize(img, (32, 24), interpolation=cv2.INTER_AREA)
    i, j = np.unravel_index(np.argmax(small), small.shape)
    # A camera ray through the old block centre lands on the new pixel centre.
    ray = np.linalg.inv(K) @ np.array([30.5, 20.5, 1.0])
    p = K2 @ ray
    np.testing.assert_allclose(p[:2] / p[2], [j, i], atol=1e-12)


def test_backproject_then_project_is_identity():
    K, T = random_camera(np.random.default_rng(3))
    depth = np.full((6, 8), 500.0)
    pts = geometry.backproject_depth(K, T, depth).reshape(-1, 3)
    px, z = geometry.project(K, T, pts)
    ys, xs = np.mgrid[0:6, 0:8]
    np.testing.assert_allclose(px, np.c_[xs.ravel(), ys.ravel()], atol=1e-6)
    np.testing.assert_allclose(z, 500.0)
