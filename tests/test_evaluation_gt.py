"""Mesh sampling, radius downsampling and the ground-truth folder writer/reader."""
import numpy as np
import open3d as o3d
import pytest
import scipy.io
from scipy.spatial import cKDTree

from pipeline.evaluation import gt as gtmod
from pipeline.evaluation.sampling import (MeshError, check_mesh, derived_seed, radius_downsample, sample_mesh,
                                         sample_triangles)

CENTRE = np.array([-28.0, -13.0, 641.0])  # scan24's object centre (DTU world, mm)


def sphere(radius=30.0, resolution=40, centre=CENTRE):
    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    return np.asarray(m.vertices) + centre, np.asarray(m.triangles)


def greedy_reference(P, r, seed):
    """The script's loop over KD-tree radius lists, in the same seeded order."""
    order = np.random.default_rng(seed).permutation(len(P))
    Q = P[order]
    mask = np.ones(len(Q), bool)
    for i, idx in enumerate(cKDTree(Q).query_ball_point(Q, r)):
        if mask[i]:
            mask[idx] = False
            mask[i] = True
    out = np.empty(len(P), bool)
    out[order] = mask
    return out


def script_triangle_samples(v0, v1, v2, thresh):
    """Direct transcription of the protocol for one triangle (np.mgrid grid, c.sum < 1)."""
    e1, e2 = v1 - v0, v2 - v0
    l1, l2 = np.linalg.norm(e1), np.linalg.norm(e2)
    thr = thresh * np.sqrt(l1 * l2 / np.linalg.norm(np.cross(e1, e2)))
    n1, n2 = np.floor(l1 / thr), np.floor(l2 / thr)
    c = np.mgrid[: n1 + 1, : n2 + 1] + 0.5
    c[0] /= max(n1, 1e-7)
    c[1] /= max(n2, 1e-7)
    k = np.transpose(c, (1, 2, 0))
    k = k[k.sum(axis=-1) < 1]
    return e1 * k[:, :1] + e2 * k[:, 1:] + v0


def test_triangle_sampling_matches_the_protocol_grid():
    rng = np.random.default_rng(0)
    V = rng.normal(size=(60, 3)) * np.array([3.0, 1.0, 0.5])
    F = rng.integers(0, 60, size=(40, 3))
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    got = sample_triangles(V, F, 0.2)
    want = np.concatenate([script_triangle_samples(*V[f], 0.2) for f in F])
    assert len(got) == len(want) > 1000
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_sampling_density_is_one_point_per_spacing_squared():
    V = np.array([[0, 0, 0], [40.0, 0, 0], [0, 30.0, 0], [40.0, 30.0, 0]])
    F = np.array([[0, 1, 2], [1, 3, 2], [0, 0, 1]])  # the last one has zero area: skipped
    pts = sample_mesh(V, F, 0.2)
    area = 40.0 * 30.0
    assert len(pts) - 4 == pytest.approx(area / 0.2**2, rel=0.02)
    assert np.all(pts[:, 2] == 0) and pts[:, 0].min() >= 0 and pts[:, 1].max() <= 30


@pytest.mark.parametrize("seed", [0, 1])
def test_radius_downsampling_equals_the_greedy_loop(seed):
    rng = np.random.default_rng(seed)
    P = rng.uniform(0, 3, size=(4000, 3))
    P[:300] = P[300:600] + rng.normal(scale=0.05, size=(300, 3))  # close pairs
    P[600:650] = P[650:700]  # exact duplicates
    keep = radius_downsample(P, 0.2, seed=seed)
    np.testing.assert_array_equal(keep, greedy_reference(P, 0.2, seed))
    kept = P[keep]
    d, _ = cKDTree(kept).query(kept, k=2)
    assert d[:, 1].min() > 0.2  # nothing kept within the radius of another kept point


def test_gt_thinning_order_is_independent_of_the_evaluation_seed(tmp_path):
    """The GT writer's stl points are the mesh's samples thinned in an order derived from
    its seed; for no evaluation seed near it is the thinning the same."""
    V, F = sphere()
    samples = sample_mesh(V, F, 0.2)
    for seed in (0, 1):
        gtmod.write_ground_truth(tmp_path / str(seed), 1001, V, F, np.array([0, 0, -1.0, 1e3]), seed=seed)
        gt_points = gtmod.read_ground_truth(tmp_path / str(seed)).points_mm
        want = samples[radius_downsample(samples, 0.2, seed=derived_seed(seed, gtmod.GT_SEED_PURPOSE))]
        np.testing.assert_allclose(gt_points, want, atol=1e-4)  # float32 storage
        for eval_seed in (0, 1, 2):
            same = samples[radius_downsample(samples, 0.2, seed=eval_seed)]
            assert len(same) != len(gt_points) or not np.allclose(same, gt_points, atol=1e-4)
    assert derived_seed(0, "a") == derived_seed(0, "a") != derived_seed(0, "b") != derived_seed(1, "b")


def test_radius_downsampling_handles_far_outliers():
    rng = np.random.default_rng(3)
    P = np.concatenate([rng.uniform(0, 2, size=(2000, 3)), [[1e12, 0, 0], [1e12 + 0.1, 0, 0], [-1e12, 5, 5]]])
    np.testing.assert_array_equal(radius_downsample(P, 0.2, seed=0), greedy_reference(P, 0.2, 0))


@pytest.mark.parametrize(
    "V, F, match",
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "no vertices"),
        (np.eye(3), np.zeros((0, 3), int), "no triangles"),
        (np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]]), np.array([[0, 1, 2]]), "zero area"),
        (np.array([[0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]]), "not finite"),
        (np.eye(3), np.array([[0, 1, 3]]), "out of range"),
    ],
)
def test_bad_meshes_are_rejected(V, F, match):
    with pytest.raises(MeshError, match=match):
        check_mesh(V, F, name="m.ply")


def test_ground_truth_round_trip(tmp_path):
    V, F = sphere()
    plane = np.array([0, 0, -1.0, CENTRE[2] + 20])  # z < centre + 20 is "above"
    written = gtmod.write_ground_truth(tmp_path / "gt", 1001, V, F, plane, res_mm=4.0)
    assert all(p.is_file() for p in written.values())
    assert not [p for p in (tmp_path / "gt").rglob(".*")]  # no temp files left behind

    g = gtmod.read_ground_truth(tmp_path / "gt")  # scan id inferred
    assert g.scan_id == 1001 and g.res_mm == 4.0
    np.testing.assert_allclose(g.plane, plane)
    # Dense, ~spacing apart, covering the surface.
    area = 4 * np.pi * 30.0**2
    assert area / 0.2**2 * 0.3 < len(g.points_mm) < area / 0.2**2
    d, _ = cKDTree(g.points_mm).query(g.points_mm, k=2)
    assert d[:, 1].min() > 0.2 - 1e-4  # float32 storage
    samples = sample_mesh(V, F, 0.1)
    gap = cKDTree(g.points_mm).query(samples)[0]
    assert gap.mean() < 0.12 and gap.max() < 0.5
    # Every point is observed; voxels 3+ voxels away from the surface are not.
    idx = g.voxel_index(g.points_mm)
    assert (idx >= 0).all() and (idx < g.obs_mask.shape).all() and g.obs_mask[tuple(idx.T)].all()
    centre_vox = tuple(g.voxel_index(CENTRE[None])[0])
    assert not g.obs_mask[centre_vox]  # 30 mm inside the sphere
    assert g.obs_mask.sum() < 0.5 * g.obs_mask.size
    assert (g.bb_mm[0] < g.points_mm.min(0)).all() and (g.bb_mm[1] > g.points_mm.max(0)).all()
    # The GT mesh is stored too.
    Vr, Fr = gtmod.read_mesh(written["mesh"])
    np.testing.assert_allclose(Vr, V, atol=1e-4)
    np.testing.assert_array_equal(Fr, F)


def test_observed_points_restrict_the_obs_mask(tmp_path):
    V, F = sphere()
    dense = sample_mesh(V, F, 0.5)
    top = dense[dense[:, 2] < CENTRE[2]]
    gtmod.write_ground_truth(tmp_path, 5, V, F, np.array([0, 0, 1.0, 0]), observed_points_mm=top, res_mm=2.0)
    g = gtmod.read_ground_truth(tmp_path, 5)
    inside = g.obs_mask[tuple(g.voxel_index(g.points_mm).T)]
    z = g.points_mm[:, 2]
    # Observed: the upper half. Dilation reaches 1-2 voxels (2-4 mm) past it, never 3.
    assert inside[z < CENTRE[2]].all() and not inside[z > CENTRE[2] + 6].any()


def test_reader_errors_name_the_file(tmp_path):
    V, F = sphere(resolution=10)
    gtmod.write_ground_truth(tmp_path, 7, V, F, np.array([0, 0, 1.0, 0]))
    gtmod.write_ground_truth(tmp_path, 8, V, F, np.array([0, 0, 1.0, 0]))
    with pytest.raises(gtmod.GroundTruthError, match="cannot infer the scan id"):
        gtmod.read_ground_truth(tmp_path)
    (tmp_path / "Points" / "stl" / "stl008_total.ply").unlink()
    with pytest.raises(FileNotFoundError, match="stl008_total.ply"):
        gtmod.read_ground_truth(tmp_path, 8)
    scipy.io.savemat(tmp_path / "ObsMask" / "ObsMask7_10.mat", {"ObsMask": np.ones((2, 2, 2)),
                                                                 "BB": np.zeros((2, 3)), "Res": 1.0})
    with pytest.raises(gtmod.GroundTruthError, match=r"ObsMask7_10.mat: BB"):
        gtmod.read_ground_truth(tmp_path, 7)
    with pytest.raises(FileNotFoundError, match="ground-truth folder"):
        gtmod.read_ground_truth(tmp_path / "nope")
    with pytest.raises(MeshError, match="ground-truth mesh"):
        gtmod.write_ground_truth(tmp_path, 9, V, np.zeros((0, 3), int), np.array([0, 0, 1.0, 0]))
