"""Closing small holes where the depth maps support it (pipeline.meshing.holes)."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.meshing.holes import depth_support, fill_supported_holes

Z_MM = 500.0
K1 = np.array([[500.0, 0.0, 50.0], [0.0, 500.0, 50.0], [0.0, 0.0, 1.0]])


def _plane_with_hole(hole_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A 2 mm grid over [-40, 40]^2 mm at camera z = 500 mm (identity pose) without the
    triangles whose centroid lies within ``hole_mm`` of the centre."""
    xs = np.arange(-40.0, 40.0 + 1e-9, 2.0)
    n = len(xs)
    X, Y = np.meshgrid(xs, xs, indexing="xy")
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, Z_MM)], 1)
    F = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            F += [[a, b, e], [a, e, d]]
    F = np.array(F, np.int64)
    keep = np.linalg.norm(V[F].mean(1)[:, :2], axis=1) > hole_mm
    return V, F[keep]


def _depth(value_in_hole: float | None = None, hole_px: int = 4) -> np.ndarray:
    d = np.zeros((1, 101, 101))
    d[0, 10:91, 10:91] = Z_MM  # the plane's footprint (+-40 mm -> +-40 px)
    if value_in_hole is not None:
        d[0, 50 - hole_px:51 + hole_px, 50 - hole_px:51 + hole_px] = value_in_hole
    return d


def _hits_centre(V, F) -> bool:
    from pipeline.raycast import MeshCaster

    hit = MeshCaster(V, F).cast(K1, np.eye(4), 101, 101).depth_mm
    return bool(hit[50, 50] > 0)


POSE = np.eye(4)[None]


def test_a_hole_the_view_sees_as_surface_is_closed_and_the_outline_is_not():
    V, F = _plane_with_hole(3.0)
    assert not _hits_centre(V, F)
    F2, facts = fill_supported_holes(V, F, _depth(), K1[None], POSE, None, radius_mm=10.0, tau_mm=1.0)
    assert facts["hole_triangles"] > 0 and facts["hole_triangles_kept"] == facts["hole_triangles"]
    assert np.array_equal(F2[:len(F)], F) and len(F2) == len(F) + facts["hole_triangles_kept"]
    assert _hits_centre(V, F2)
    # The outer boundary (radius ~57 mm) is beyond 10 mm: the plane is not closed into a box.
    assert facts["hole_triangles"] < 20


def test_holes_beyond_the_radius_stay_open():
    V, F = _plane_with_hole(3.0)
    F2, facts = fill_supported_holes(V, F, _depth(), K1[None], POSE, None, radius_mm=1.0, tau_mm=1.0)
    assert np.array_equal(F2, F) and facts["hole_triangles"] == 0
    F3, facts = fill_supported_holes(V, F, _depth(), K1[None], POSE, None, radius_mm=0.0, tau_mm=1.0)
    assert np.array_equal(F3, F) and facts == {"hole_triangles": 0, "hole_triangles_kept": 0}


@pytest.mark.parametrize("case", ["recess", "outside_mask", "no_depth"])
def test_a_hole_the_views_see_through_or_not_at_all_stays_open(case):
    V, F = _plane_with_hole(3.0)
    masks = None
    if case == "recess":  # the view sees 20 mm behind the plane there: a window, not a hole
        depth = _depth(Z_MM + 20.0)
    elif case == "no_depth":  # no view has depth there: nothing supports a surface
        depth = _depth(0.0)
    else:
        depth = _depth()
        masks = np.ones((1, 101, 101), bool)
        masks[0, 46:55, 46:55] = False
    F2, facts = fill_supported_holes(V, F, depth, K1[None], POSE, masks, radius_mm=10.0, tau_mm=1.0)
    assert facts["hole_triangles"] > 0 and facts["hole_triangles_kept"] == 0
    assert np.array_equal(F2, F)


def test_depth_support_matches_a_point_loop():
    rng = np.random.default_rng(3)
    N, H, W = 3, 30, 40
    K = np.stack([np.array([[60.0, 0, 19.5], [0, 60.0, 14.5], [0, 0, 1]])] * N)
    T = np.stack([np.eye(4)] * N)
    for i in range(1, N):
        a = 0.1 * i  # about the y axis
        T[i, :3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
        T[i, 0, 3] = 3.0 * i
    depths = rng.uniform(40, 60, (N, H, W)) * (rng.random((N, H, W)) > 0.2)
    masks = rng.random((1, H, W)) > 0.3  # the first view only
    P = np.stack([rng.uniform(-15, 15, 400), rng.uniform(-12, 12, 400), rng.uniform(35, 65, 400)], 1)
    tau = 2.0
    sup, thr = depth_support(P, depths, K, T, masks, tau)
    for p in range(len(P)):
        s = t = False
        for i in range(N):
            c = T[i, :3, :3] @ P[p] + T[i, :3, 3]
            if c[2] <= 0:
                continue
            u, v = np.rint(K[i, 0, 0] * c[0] / c[2] + K[i, 0, 2]), np.rint(K[i, 1, 1] * c[1] / c[2] + K[i, 1, 2])
            if not (0 <= u < W and 0 <= v < H):
                continue
            d = depths[i, int(v), int(u)]
            s |= d > 0 and abs(c[2] - d) <= tau
            t |= d > 0 and c[2] < d - tau
            t |= i == 0 and not masks[0, int(v), int(u)]
        assert (sup[p], thr[p]) == (s, t), p
    assert 0 < sup.sum() < len(P) and 0 < thr.sum() < len(P)


@pytest.mark.parametrize("bad", [-0.1, float("inf"), float("nan")])
def test_the_config_rejects_a_bad_hole_radius(bad):
    from pipeline.config.mesh import MeshConfig
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="mesh.fill_holes_norm"):
        MeshConfig.default(fill_holes_norm=bad)
    assert MeshConfig.default(fill_holes_norm=0.0).fill_holes_norm == 0.0
