"""End to end: ``gcgs synth`` writes a scene and its GT, ``gcgs evaluate`` scores offset meshes."""
import json

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
