"""End to end: ``gcgs synth`` writes a scene and its GT, ``gcgs evaluate`` scores offset meshes."""
import json
import math

import numpy as np
import open3d as o3d
import pytest

from pipeline.cli import main
from pipeline.evaluation import gt as gtmod


@pytest.mark.slow
def test_synth_then_evaluate_offset_meshes(tmp_path, bundled_scan):
    scene = tmp_path / "synth_textureless"
    assert main(["synth", "synth_textureless", "--out", str(scene), "--width", "160", "--height", "120",
                 "--cameras", str(bundled_scan)]) == 0
    mesh = o3d.io.read_triangle_mesh(str(scene / "gt" / "mesh.ply"))
    mesh.compute_vertex_normals()
    V, F, N = np.asarray(mesh.vertices), np.asarray(mesh.triangles), np.asarray(mesh.vertex_normals)
    # The scene is smooth (curvature radii >> 2 mm), so offsetting along the vertex normals
    # moves the surface by delta everywhere.
    for delta in (0.5, 2.0):
        gtmod.write_ply_mesh(tmp_path / "offset.ply", V + delta * N, F)
        out = tmp_path / f"metrics_{delta}.json"
        assert main(["evaluate", "--mesh", str(tmp_path / "offset.ply"), "--scene", str(scene),
                     "--out", str(out)]) == 0
        m = json.loads(out.read_text())
        assert m["config"]["cull_view_ids"] == [23, 24, 33]  # params: cull the input views
        assert m["accuracy_mm"] == pytest.approx(delta, rel=0.1)
        assert m["completeness_mm"] == pytest.approx(delta, rel=0.1)
        assert m["overall_mm"] == pytest.approx((m["accuracy_mm"] + m["completeness_mm"]) / 2)
    # The split by input views seeing the surface (issue 19): every GT point is within
    # max_dist of the offset mesh, so the groups' means weighted by their fractions give the
    # overall completeness back, and the surface the views see is off by delta too.
    from pipeline.config.evaluate import EvaluateConfig
    from pipeline.evaluation import dtu_eval, seen

    m = dtu_eval.evaluate_mesh(*gtmod.read_mesh(tmp_path / "offset.ply"), gtmod.read_ground_truth(scene / "gt", None),
                               EvaluateConfig.default(), log=None, seen_views=seen.load_input_views(scene, [23, 24, 33]))
    acc, comp = m["accuracy_by_views_seen"], m["completeness_by_views_seen"]
    assert m["counts"]["completeness_used"] == m["counts"]["gt_above_plane"]
    assert sum(g["fraction"] for g in comp.values()) == pytest.approx(1.0)
    assert sum(g["fraction"] * g["completeness_mm"] for g in comp.values() if g["fraction"] > 0) == pytest.approx(
        m["completeness_mm"])
    assert comp["2+"]["fraction"] > 0.3 and comp["2+"]["completeness_mm"] == pytest.approx(delta, rel=0.1)
    assert acc["2+"]["accuracy_mm"] == pytest.approx(delta, rel=0.1)


# --- accuracy split by the input views that see the surface (issue 19) ---------------------------

def _looking_down(x_mm: float) -> np.ndarray:
    """World-to-camera of a camera at (x, 0, 500) mm looking straight down (-z)."""
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[:3, 3] = [-x_mm, 0.0, 500.0]
    return T


def _seen_fixture():
    from pipeline.evaluation.seen import InputView

    K = np.array([[250.0, 0, 49.5], [0, 250.0, 49.5], [0, 0, 1]])  # +-100 mm wide at the ground
    views = [InputView(K, _looking_down(x), 100, 100) for x in (-30.0, 0.0, 30.0)]
    ground = np.array([[-300, -300, 0], [300, -300, 0], [300, 300, 0], [-300, 300, 0.0]])
    # A small square at z = 250 on the ray from the camera at x = 30 to (-45, 0, 0) only.
    occluder = np.array([[-10, -3, 250], [-5, -3, 250], [-5, 3, 250], [-10, 3, 250.0]])
    V = np.concatenate([ground, occluder])
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return V, F, views


def test_views_seeing_counts_image_bounds_and_occlusion():
    from pipeline.evaluation.seen import views_seeing

    V, F, views = _seen_fixture()
    points = np.array([[0, 0, 0], [-45, 0, 0], [120, 0, 0], [200, 0, 0.0]])
    # all three; the occluder hides it from x = 30; only x = 30 has it in its image; none
    np.testing.assert_array_equal(views_seeing(points, V, F, views), [3, 2, 1, 0])


def test_completeness_by_views_seen_groups_the_gt_points_themselves():
    from pipeline.evaluation.seen import completeness_by_views_seen

    V, F, views = _seen_fixture()
    # seen by 3, 2 (occluded from x = 30), 1, 0 views; the last two "2+" points: one beyond
    # max_dist (left out of the mean, not of the fraction), one at inf (beyond the search)
    gt_points = np.array([[0, 0, 0], [-45, 0, 0], [120, 0, 0], [200, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    dist = np.array([0.2, 0.6, 3.0, 9.0, 25.0, np.inf])
    r = completeness_by_views_seen(gt_points, dist, V, F, views, max_dist_mm=20.0)
    assert r["2+"]["fraction"] == pytest.approx(4 / 6) and r["2+"]["completeness_mm"] == pytest.approx(0.4)
    assert r["1"]["fraction"] == pytest.approx(1 / 6) and r["1"]["completeness_mm"] == pytest.approx(3.0)
    assert r["0"]["fraction"] == pytest.approx(1 / 6) and r["0"]["completeness_mm"] == pytest.approx(9.0)
    with pytest.raises(ValueError, match="6 GT points but 5 distances"):
        completeness_by_views_seen(gt_points, dist[:5], V, F, views, max_dist_mm=20.0)
    empty = completeness_by_views_seen(np.zeros((0, 3)), np.zeros(0), V, F, views, max_dist_mm=20.0)
    assert all(math.isnan(g["completeness_mm"]) for g in empty.values())


def test_accuracy_by_views_seen_groups_by_the_nearest_gt_point():
    from pipeline.evaluation.seen import accuracy_by_views_seen

    V, F, views = _seen_fixture()
    gt_points = np.array([[0, 0, 0], [120, 0, 0], [200, 0, 0.0]])
    data = gt_points + np.array([[0, 0, 0.3], [0, 0, 0.5], [0, 0, 0.7]])
    data = np.concatenate([data, [[0.2, 0, 0], [200, 0, 30.0]]])  # one more "2+"; one beyond max_dist
    r = accuracy_by_views_seen(data, gt_points, V, F, views, max_dist_mm=20.0)
    assert r["2+"]["fraction"] == pytest.approx(0.4) and r["2+"]["accuracy_mm"] == pytest.approx(0.25)
    assert r["1"]["fraction"] == pytest.approx(0.2) and r["1"]["accuracy_mm"] == pytest.approx(0.5)
    assert r["0"]["fraction"] == pytest.approx(0.4) and r["0"]["accuracy_mm"] == pytest.approx(0.7)
