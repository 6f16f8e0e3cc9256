"""The report page (``gcgs report-index``) and the per-scene pictures (``gcgs render-scene``)."""
import json
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from init_scene import make_scene
from pipeline.cli import main
from pipeline.data import dtu
from pipeline.errors import MissingInputError
from pipeline.evaluation import gt
from pipeline.reports.renders import scene_panels, write_png
from pipeline.reports.index import index_markdown
from pipeline.optimize.seed import init_params
from pipeline.surfels import write_surfel_ply

LABEL_ROWS = 16  # the panels' text labels


@pytest.fixture(scope="module")
def sphere_scene(tmp_path_factory):
    """One textured sphere (world mm) at 160x120: the prepared scene, surfels on the sphere
    with outward normals, the sphere's mesh, and the exact depth of the first view."""
    tmp = tmp_path_factory.mktemp("render")
    base = dtu.load_scene(Path(__file__).resolve().parents[1] / "data/raw/dtu/scan24", resolution=(160, 120))
    centre, radius = base.norm_to_world[:3, 3], 0.35 * base.norm_scale_mm
    scene, depths = make_scene(160, 120, spheres=[(centre, radius)])
    dtu.write_scene(tmp / "scene", dict(zip(scene.view_ids, scene.images)), dict(zip(scene.view_ids, scene.K)),
                    dict(zip(scene.view_ids, scene.world_to_cam)), scene.norm_to_world,
                    masks=dict(zip(scene.view_ids, scene.masks)))
    n = 20000  # a Fibonacci sphere, dense enough to cover the silhouette
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    normals = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    s = scene.norm_scale_mm
    points_norm = (centre - scene.norm_to_world[:3, 3]) / s + normals * radius / s
    params = init_params(points_norm, normals, np.full((n, 3), 0.6), 0, 0.99, np.random.default_rng(0))
    write_surfel_ply(tmp / "surfels.ply", params, scene.norm_to_world)
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=60).translate(centre)
    gt.write_ply_mesh(tmp / "mesh.ply", np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    return tmp, scene, depths[0] > 0


def test_panels_show_input_surfels_and_mesh_at_the_first_view(sphere_scene):
    tmp, scene, silhouette = sphere_scene
    rgb = scene_panels(tmp / "scene", tmp / "surfels.ply", tmp / "mesh.ply", panel_width=160)
    assert rgb.shape == (120, 640, 3) and rgb.dtype == np.uint8
    image, colour, normal, mesh = (rgb[LABEL_ROWS:, k * 160:(k + 1) * 160].astype(float) for k in range(4))
    sil = silhouette[LABEL_ROWS:]
    want = np.clip(dtu.load_scene(tmp / "scene", view_ids=None).images[0][LABEL_ROWS:] * 255, 0, 255)
    assert np.abs(image - want).max() <= 1
    # Covered where the sphere is, black elsewhere (surfels: more than half of their grey 0.6).
    for covered in (colour.mean(-1) > 0.3 * 255, mesh.sum(-1) > 0):
        assert (covered & sil).sum() / (covered | sil).sum() > 0.9
    # A sphere facing the camera: blue (z towards the viewer) high at its centre, and the
    # x component (red) growing from its left edge to its right edge.
    ys, xs = np.nonzero(sil)
    cy, cx = int(ys.mean()), int(xs.mean())
    assert normal[cy, cx, 2] > 0.9 * 255
    row = np.nonzero(sil[cy])[0]
    assert normal[cy, row[1], 0] < 0.3 * 255 < 0.7 * 255 < normal[cy, row[-2], 0]
    assert mesh[cy, cx, 0] > mesh[cy, row[1], 0]  # headlight: brighter where the surface faces the camera


def test_render_scene_command_writes_a_small_png(sphere_scene, tmp_path):
    tmp, _, _ = sphere_scene
    out = tmp_path / "renders" / "s.png"
    assert main(["render-scene", "--scene", str(tmp / "scene"), "--surfels", str(tmp / "surfels.ply"),
                 "--mesh", str(tmp / "mesh.ply"), "--out", str(out)]) == 0
    assert 0 < out.stat().st_size <= 200_000


def test_png_of_a_busy_picture_stays_under_200_kb(tmp_path):
    noise = np.random.default_rng(0).integers(0, 256, (120, 640, 3), dtype=np.uint8)
    write_png(tmp_path / "n.png", noise)  # incompressible: the worst case of four 160 px panels
    assert (tmp_path / "n.png").stat().st_size <= 240_000
    image = dtu.load_scene(Path(__file__).resolve().parents[1] / "data/raw/dtu/scan24", resolution=(160, 120)).images
    write_png(tmp_path / "s.png", (np.concatenate(list(image[:3]) + [image[0]], 1) * 255).astype(np.uint8))
    assert (tmp_path / "s.png").stat().st_size <= 200_000


def _reports(root: Path) -> dict:
    (root / "metrics").mkdir(parents=True)
    (root / "table1.md").write_text("# Table I: overall Chamfer\n\n| method | x |\n| --- | --- |\n| a | 1 |\n")
    train = {"preset": "fast", "iterations": 500, "backend": "cpu", "surfels_final": 123}
    timing = {"wall_s": 61.4, "cpu_s": 70.2, "peak_rss_mb": 900.0}
    mesh = {"triangles_kept": 10, "components_kept": 1, "views_virtual": 0}
    (root / "metrics/synth_a.json").write_text(json.dumps({
        "scene": "synth_a", "train": train, "timing": timing, "mesh": mesh,
        "chamfer": {"accuracy_mm": 0.5, "completeness_mm": 1.5, "overall_mm": 1.0, "valid": True, "problems": []}}))
    (root / "metrics/scan24.json").write_text(json.dumps({
        "scene": "scan24", "train": train | {"preset": "paper"}, "timing": timing, "mesh": mesh,
        "heldout": {"views": 46, "size": [200, 150], "iou_mean": 0.9, "hull_iou_mean": 0.7,
                    "psnr_masked_db_mean": 16.46, "per_view": {}}}))
    (root / "renders").mkdir()
    (root / "renders/scan24.png").write_bytes(b"png")
    (root / "renders/scan24_heldout.png").write_bytes(b"png")
    (root / "train/scan24/plots/metrics/train").mkdir(parents=True)
    (root / "train/scan24/plots/metrics/train/total.tsv").write_text("step\ttotal\n0\t1.0\n")
    return {"synth_a": {"src": "data/synth/synth_a", "gt": "data/synth/synth_a/gt"},
            "scan24": {"src": "data/raw/dtu/scan24", "gt": None}}


def test_index_shows_what_exists_with_its_source(tmp_path):
    scenes = _reports(tmp_path)
    md = index_markdown(tmp_path, scenes, "abc1234")
    assert "at commit `abc1234`" in md
    assert "## Table I: overall Chamfer" in md and "| a | 1 |" in md and "(the file [`table1.md`](table1.md))" in md
    assert "Table II" not in md and "speed_accuracy.png" not in md
    assert "| overall = (accuracy + completeness) / 2 | 1.000 |" in md
    assert "| mask IoU of the surfels (alpha > 0.5) | 0.900 |" in md and "| PSNR over the mask (dB) | 16.46 |" in md
    assert "preset **paper**, 500 iterations" in md and "61 s wall" in md
    assert "](renders/scan24.png)" in md and "renders/synth_a.png" not in md
    assert "](renders/scan24_heldout.png)" in md and "renders/synth_a_heldout.png" not in md
    assert "[total](train/scan24/plots/metrics/train/total.tsv)" in md

    (tmp_path / "table2.md").write_text("# Table II\n\n| variant | mean |\n| --- | --- |\n| full | 1 |\n")
    (tmp_path / "speed_accuracy.png").write_bytes(b"png")
    md = index_markdown(tmp_path, scenes, "abc1234")
    assert "## Table II" in md and "| full | 1 |" in md
    assert "](speed_accuracy.png)" in md


def test_index_names_a_missing_metrics_file_and_writes_nothing(tmp_path, capsys):
    scenes = _reports(tmp_path)
    (tmp_path / "metrics/synth_a.json").unlink()
    with pytest.raises(MissingInputError, match=r"metrics/synth_a\.json: no metrics \(file not found; run the score stage"):
        index_markdown(tmp_path, scenes, "x")
    params = tmp_path / "params.yaml"
    params.write_text(json.dumps({"scenes": scenes}))
    assert main(["report-index", "--reports-dir", str(tmp_path), "--params", str(params)]) == 1
    assert "synth_a.json" in capsys.readouterr().err and not (tmp_path / "index.md").exists()
