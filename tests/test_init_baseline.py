"""Cloud-vs-GT figures of the baseline (pipeline.evaluation.clouds)."""
from __future__ import annotations

import numpy as np
import pytest

from pipeline.config.evaluate import EvaluateConfig
from pipeline.evaluation.clouds import cloud_metrics
from pipeline.evaluation.gt import read_ground_truth, write_ground_truth


@pytest.fixture(scope="module")
def sphere_gt(tmp_path_factory):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_sphere(radius=50.0, resolution=60)
    V = np.asarray(m.vertices) + [0.0, 0.0, 600.0]
    root = tmp_path_factory.mktemp("gt")
    # Ground plane z = 560: the GT "above the plane" is the cap z > 560.
    write_ground_truth(root, 1001, V, np.asarray(m.triangles), np.array([0.0, 0.0, 1.0, -560.0]), spacing_mm=1.0)
    return read_ground_truth(root, 1001)


def _on_sphere(n, rng, radius=50.0):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * radius + [0.0, 0.0, 600.0]


def test_cloud_on_the_surface_scores_near_zero(sphere_gt):
    rng = np.random.default_rng(0)
    m = cloud_metrics(_on_sphere(100000, rng), sphere_gt, EvaluateConfig.default())  # ~0.6 mm apart
    assert m["surface"] == "GT mesh"
    assert m["median_to_surface_mm"] < 0.05  # tessellation of the GT sphere only
    assert m["precision_1mm"] == 1.0 and m["recall_1mm"] > 0.99
    assert m["accuracy_mm"] < 1.0 and m["completeness_mm"] < 1.0  # GT points are 1-2 mm apart


def test_cloud_offset_is_measured(sphere_gt):
    rng = np.random.default_rng(1)
    m = cloud_metrics(_on_sphere(20000, rng, radius=52.0), sphere_gt, EvaluateConfig.default())
    assert m["median_to_surface_mm"] == pytest.approx(2.0, abs=0.05)
    assert m["precision_1mm"] == 0.0
    # Half a sphere: the lower half is missing from the cloud, the GT cap is above z = 560.
    half = _on_sphere(20000, rng)
    half = half[half[:, 2] > 600.0]
    m2 = cloud_metrics(half, sphere_gt, EvaluateConfig.default())
    assert m2["recall_1mm"] < 0.8 and m2["completeness_mm"] > 1.0
