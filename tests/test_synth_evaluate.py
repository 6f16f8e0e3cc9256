"""End to end: `gcgs synth` then `gcgs evaluate` on the GT mesh offset along its normals.

The textureless scene is smooth (an ellipsoid on a plinth), so a surface offset by delta
along vertex normals lies delta from the original everywhere but at the plinth rim; the
Chamfer terms must then read delta. (Box corners with shared, averaged normals or bumps
with curvature radius below delta would not give a clean delta offset.)
"""
import json

import numpy as np
import open3d as o3d
import pytest

from pipeline.cli import main as gcgs
from pipeline.evaluation.gt import read_mesh, write_ply_mesh


@pytest.fixture(scope="module")
def textureless(tmp_path_factory, bundled_scan):
    out = tmp_path_factory.mktemp("e2e") / "textureless"
    assert gcgs(["synth", "synth_textureless", "--out", str(out), "--width", "200", "--height", "150",
                 "--cameras", str(bundled_scan)]) == 0
    return out


@pytest.mark.parametrize("delta_mm", [0.5, 2.0])
def test_offset_gt_mesh_gives_delta(textureless, tmp_path, delta_mm):
    V, F = read_mesh(textureless / "gt" / "mesh.ply")
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F))
    mesh.compute_vertex_normals()
    offset = tmp_path / "offset.ply"
    write_ply_mesh(offset, V + delta_mm * np.asarray(mesh.vertex_normals), F)
    out = tmp_path / "metrics.json"
    assert gcgs(["evaluate", "--mesh", str(offset), "--scene", str(textureless), "--out", str(out)]) == 0
    m = json.loads(out.read_text())
    assert m["accuracy_mm"] == pytest.approx(delta_mm, rel=0.10)
    assert m["completeness_mm"] == pytest.approx(delta_mm, rel=0.10)
    assert m["overall_mm"] == pytest.approx((m["accuracy_mm"] + m["completeness_mm"]) / 2)
