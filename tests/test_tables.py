"""Table I (``gcgs table1``, :mod:`pipeline.reports.table1`): measured cells come from the
per-scene reports, published ones from the data file and never the other way round; bad
reports are named; the written CSV and Markdown parse; a DTU scan added to params fills
its column with no code change."""
import csv
import json
import re
import shutil
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
import yaml

from pipeline.cli import main
from pipeline.errors import InputError, MissingInputError
from pipeline.reports import table1 as tables

REPO = Path(__file__).resolve().parents[1]
PUBLISHED = REPO / "data" / "published" / "dtu_3view_table1.csv"


def _metrics(overall=None, heldout=None, preset="fast", iterations=500) -> dict:
    m = {"scene": "s", "train": {"preset": preset, "iterations": iterations, "backend": "cpu", "masks": True,
                                 "surfels_init": 10, "surfels_final": 20},
         "timing": {"wall_s": 1.0, "cpu_s": 1.0, "peak_rss_mb": 100.0},
         "mesh": {"triangles_kept": 10, "components_kept": 1, "views_virtual": 0}}
    if overall is not None:
        m["chamfer"] = {"accuracy_mm": overall, "completeness_mm": overall, "overall_mm": overall,
                        "valid": True, "problems": []}
    if heldout is not None:
        m["heldout"] = {"views": 4, "size": [200, 150], "iou_mean": heldout[0], "hull_iou_mean": heldout[1],
                        "psnr_masked_db_mean": heldout[2], "per_view": {}}
        if len(heldout) > 3:
            m["heldout"]["mesh_iou_mean"] = heldout[3]
    return m


def _baseline(overall, commit="abc123") -> dict:
    return {"commit": commit, "evaluate": {"status": "ok", "metrics": {
        "accuracy_mm": overall, "completeness_mm": overall, "overall_mm": overall, "valid": True, "problems": []}}}


@pytest.fixture
def reports(tmp_path):
    """Reports of two synthetic scenes, one DTU scan with GT and one real scan without."""
    metrics, baseline = tmp_path / "metrics", tmp_path / "baseline"
    metrics.mkdir()
    baseline.mkdir()
    values = {"synth_a": (1.5, 2.5), "synth_b": (2.5, 3.5), "scan37": (0.75, 1.25)}
    for name, (ours, theirs) in values.items():
        (metrics / f"{name}.json").write_text(json.dumps(_metrics(ours)))
        (baseline / f"{name}.json").write_text(json.dumps(_baseline(theirs)))
    (metrics / "scan24.json").write_text(json.dumps(_metrics(heldout=(0.9, 0.7, 16.5, 0.85))))
    scenes = {"scan24": {"src": "x", "gt": None}, "synth_a": {"src": "a", "gt": "a/gt"},
              "synth_b": {"src": "b", "gt": "b/gt"}, "scan37": {"src": "s", "gt": "dtu"}}
    return scenes, metrics, baseline, values


def _published_columns() -> list[str]:
    with PUBLISHED.open() as fh:
        return next(csv.reader(fh))


def _row(table, method):
    return next(r for r in table.rows if r.method == method)


def test_measured_cells_come_from_the_reports_and_published_from_the_data_file(reports):
    scenes, metrics, baseline, values = reports
    table = tables.build_table1(scenes, metrics, baseline, PUBLISHED, "deadbee")
    assert table.scenes_synthetic == ["synth_a", "synth_b"] and table.scenes_dtu[0] == "scan37"
    assert sorted(table.scenes_dtu) == sorted({"scan37"} | {c for c in _published_columns() if c.startswith("scan")})
    ours, theirs = _row(table, "GCGS (this pipeline)"), _row(table, "MVS + TSDF (classical baseline)")
    for i, row in enumerate((ours, theirs)):
        assert row.kind == tables.MEASURED
        for name, v in values.items():
            assert row.cells[name] == v[i]
        assert row.cells[tables.MEAN_SYNTH] == pytest.approx((values["synth_a"][i] + values["synth_b"][i]) / 2)
        assert row.cells[tables.MEAN_DTU] == values["scan37"][i]
    assert ours.commit == "deadbee" and theirs.commit == "abc123"

    published = tables.read_published(PUBLISHED)
    assert [r for r in table.rows if r.kind == tables.PUBLISHED] == published
    measured_values = {v for r in (ours, theirs) for v in r.cells.values()}
    with PUBLISHED.open() as fh:
        file_rows = {rec["method"]: rec for rec in csv.DictReader(fh)}
    for r in published:
        # Published rows hold no synthetic (measured-only) cell, and every figure they hold,
        # per DTU scan and mean, is the file's own: none comes from a measurement.
        assert all(r.cells.get(s) is None for s in ["synth_a", "synth_b", tables.MEAN_SYNTH])
        rec = file_rows[r.method]
        assert r.cells[tables.MEAN_DTU] == (float(rec["mean_mm"]) if rec["mean_mm"] else None)
        for scan in (c for c in rec if c.startswith("scan")):
            assert r.cells.get(scan) == (float(rec[scan]) if rec[scan] else None)
        assert r.cells[tables.MEAN_DTU] is None or r.cells[tables.MEAN_DTU] not in measured_values

    assert [(h.scene, h.iou, h.hull_iou, h.psnr_masked_db, h.mesh_iou) for h in table.heldout] == \
        [("scan24", 0.9, 0.7, 16.5, 0.85)]


def test_repository_published_file_has_sources_and_no_figure_without_one():
    rows = tables.read_published(PUBLISHED)
    assert len(rows) >= 12
    for r in rows:
        assert r.source
        if r.cells[tables.MEAN_DTU] is None:
            assert "not available offline" in r.note


def test_written_csv_and_markdown_parse(reports, tmp_path):
    scenes, metrics, baseline, _ = reports
    table = tables.build_table1(scenes, metrics, baseline, PUBLISHED, "deadbee")
    rows = tables.read_table_csv(tables.csv_text(table))
    assert [r["method"] for r in rows] == [r.method for r in table.rows]
    for parsed, row in zip(rows, table.rows):
        assert parsed["kind"] == row.kind
        for col in table.columns:
            want = row.cells.get(col)
            assert parsed["cells"][col] == (None if want is None else pytest.approx(want, abs=1e-4))

    md = tables.markdown(table, "deadbee")
    chamfer = [ln for ln in md.splitlines() if "| measured here |" in ln or "| published |" in ln]
    header = next(ln for ln in md.splitlines() if ln.startswith("| method |"))
    assert len(chamfer) == len(table.rows)
    assert all(ln.count("|") == header.count("|") for ln in chamfer)
    assert "| scan24 | 4 | 200x150 | 0.850 | 0.900 | 0.700 | 16.50 |" in md


def test_read_table_csv_rejects_a_non_number(reports):
    scenes, metrics, baseline, _ = reports
    text = tables.csv_text(tables.build_table1(scenes, metrics, baseline, PUBLISHED, "x"))
    bad = text.replace("1.5000", "1.5mm", 1)
    with pytest.raises(tables.ReportError, match=r"table1.csv: line 2: synth_a must be a number"):
        tables.read_table_csv(bad, "table1.csv")


@pytest.mark.parametrize("damage, message", [
    (lambda p: p.unlink(), r"synth_b\.json: no metrics \(file not found"),
    (lambda p: p.write_text("{not json"), r"synth_b\.json: metrics are not valid JSON"),
    (lambda p: p.write_text(json.dumps(_metrics(1.0) | {"chamfer": {"overall_mm": None, "valid": True}})),
     r"synth_b\.json: chamfer: `accuracy_mm` must be a number, got None"),
    (lambda p: p.write_text(json.dumps(_metrics(1.0) | {"chamfer": {"accuracy_mm": None, "completeness_mm": 1.0,
                                                                     "overall_mm": None, "valid": False,
                                                                     "problems": ["no data point"]}})),
     r"synth_b\.json: Chamfer overall, accuracy undefined \(no data point\)"),
    (lambda p: p.write_text(json.dumps({"train": {}})), r"synth_b\.json: missing `scene`, `timing`, `mesh`"),
])
def test_bad_metrics_file_is_named_and_nothing_written(reports, tmp_path, capsys, damage, message):
    scenes, metrics, baseline, _ = reports
    damage(metrics / "synth_b.json")
    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"scenes": scenes}))
    out_md, out_csv = tmp_path / "t.md", tmp_path / "t.csv"
    assert main(["table1", "--metrics-dir", str(metrics), "--baseline-dir", str(baseline), "--params", str(params),
                 "--out-md", str(out_md), "--out-csv", str(out_csv)]) == 1
    err = capsys.readouterr().err
    assert str(metrics / "synth_b.json") in err
    assert re.search(message, err)
    assert not out_md.exists() and not out_csv.exists()


def test_missing_baseline_report_and_missing_heldout_are_named(reports):
    scenes, metrics, baseline, _ = reports
    (baseline / "scan37.json").unlink()
    with pytest.raises(MissingInputError, match=r"scan37\.json: no baseline report of scene scan37"):
        tables.build_table1(scenes, metrics, baseline, PUBLISHED, "x")
    (metrics / "scan24.json").write_text(json.dumps(_metrics()))
    with pytest.raises(InputError, match=r"scan24\.json: exactly one of `chamfer` .* and `heldout` expected"):
        tables.build_table1({"scan24": scenes["scan24"]}, metrics, baseline, PUBLISHED, "x")


@pytest.mark.parametrize("text, message", [
    ("method,mean_mm,source,note\nX,1.2mm,paper,\n", r"line 2: mean_mm must be a number or empty"),
    ("method,mean_mm,source,note\nX,-1,paper,\n", r"line 2: mean_mm must be a positive number"),
    ("method,mean_mm,source\nX,1,paper\n", r"missing column\(s\) \['note'\]"),
    ("method,mean_mm,source,note,ours\nX,1,paper,,2\n", r"unknown column\(s\) \['ours'\]"),
])
def test_bad_published_file_is_named(tmp_path, text, message):
    path = tmp_path / "published.csv"
    path.write_text(text)
    with pytest.raises(tables.ReportError, match=rf"published\.csv: {message}"):
        tables.read_published(path)


def test_published_per_scan_figure_gets_its_own_column(reports, tmp_path):
    scenes, metrics, baseline, _ = reports
    path = tmp_path / "published.csv"
    path.write_text("method,mean_mm,source,note,scan37,scan122\nPaperNet,0.9,a paper,,0.8,1.1\n")
    table = tables.build_table1(scenes, metrics, baseline, path, "x")
    assert table.scenes_dtu == ["scan37", "scan122"]
    paper = _row(table, "PaperNet")
    assert (paper.kind, paper.cells["scan37"], paper.cells["scan122"]) == (tables.PUBLISHED, 0.8, 1.1)
    # The measured DTU mean stays over the measured scans only.
    assert _row(table, "GCGS (this pipeline)").cells[tables.MEAN_DTU] == 0.75


# --- a DTU scan in the official layout, pointed at by params only ---------------------------


def _fake_dtu(synth_scene: Path, root: Path, scan: int) -> tuple[Path, Path]:
    """The synthetic scene rearranged as DTU ships it: ``root/scanNN`` with the images,
    masks and cameras (no scene.json), and ``root/SampleSet/MVS Data`` with ObsMask and the
    stl points named by the scan number."""
    src, gt_root = root / f"scan{scan}", root / "SampleSet" / "MVS Data"
    for sub in ("image", "mask"):
        shutil.copytree(synth_scene / sub, src / sub)
    shutil.copy(synth_scene / "cameras_sphere.npz", src)
    old = json.loads((synth_scene / "scene.json").read_text())["scan_id"]
    (gt_root / "ObsMask").mkdir(parents=True)
    (gt_root / "Points" / "stl").mkdir(parents=True)
    shutil.copy(synth_scene / "gt/ObsMask" / f"ObsMask{old}_10.mat", gt_root / "ObsMask" / f"ObsMask{scan}_10.mat")
    shutil.copy(synth_scene / "gt/ObsMask" / f"Plane{old}.mat", gt_root / "ObsMask" / f"Plane{scan}.mat")
    shutil.copy(synth_scene / "gt/Points/stl" / f"stl{old:03d}_total.ply",
                gt_root / "Points" / "stl" / f"stl{scan:03d}_total.ply")
    return src, gt_root


@pytest.mark.slow
def test_dtu_scan_in_params_fills_its_column(tmp_path, bundled_scan, monkeypatch):
    synth = tmp_path / "synth"
    assert main(["synth", "synth_textureless", "--out", str(synth), "--width", "160", "--height", "120",
                 "--cameras", str(bundled_scan)]) == 0
    src, gt_root = _fake_dtu(synth, tmp_path / "DTU", 105)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["data"].update(width=160, height=120)
    params["scenes"] = {"scan105": {"src": str(src), "gt": str(gt_root)}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    monkeypatch.chdir(tmp_path)
    assert main(["prepare", "--src", str(src), "--out", "scenes/scan105", "--name", "scan105"]) == 0

    # Stand-ins for the optimize and mesh outputs: the GT mesh moved 0.5 mm along its
    # normals (a smooth scene, so every point moves by 0.5 mm), scored by the real evaluator.
    mesh = o3d.io.read_triangle_mesh(str(synth / "gt" / "mesh.ply"))
    mesh.compute_vertex_normals()
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) + 0.5 * np.asarray(mesh.vertex_normals))
    Path("meshes").mkdir()
    o3d.io.write_triangle_mesh("meshes/mesh.ply", mesh)
    Path("meshes/mesh.json").write_text(json.dumps({"triangles_kept": len(mesh.triangles), "components_kept": 1,
                                                    "views_virtual": 0}))
    Path("surfels").mkdir()
    Path("surfels/train.json").write_text(json.dumps(_metrics()["train"] | {"removed_degenerate": 0}))
    Path("timing.json").write_text(json.dumps({"wall_s": 1.0, "cpu_s": 1.0, "s_per_iteration": 0.1,
                                               "peak_rss_mb": 1.0, "split_s": {}}))
    assert main(["score", "scan105", "--scene", "scenes/scan105", "--surfels-dir", "surfels", "--mesh-dir", "meshes",
                 "--train-timing", "timing.json", "--out", "reports/metrics/scan105.json"]) == 0
    Path("reports/baseline").mkdir()
    Path("reports/baseline/scan105.json").write_text(json.dumps({"commit": "t", "evaluate": {"status": "not run"}}))

    assert main(["table1", "--published", str(PUBLISHED)]) == 0
    overall = json.loads(Path("reports/metrics/scan105.json").read_text())["chamfer"]["overall_mm"]
    assert overall == pytest.approx(0.5, rel=0.2)
    rows = {r["method"]: r for r in tables.read_table_csv(Path("reports/table1.csv").read_text())}
    ours = rows["GCGS (this pipeline)"]["cells"]
    assert ours["scan105"] == pytest.approx(overall, abs=1e-4)
    assert ours[tables.MEAN_DTU] == pytest.approx(overall, abs=1e-4)
    assert rows["MVS + TSDF (classical baseline)"]["cells"]["scan105"] is None
    paper = next(r for r in tables.read_published(PUBLISHED) if r.method == "GCGS")
    assert rows["GCGS"]["cells"]["scan105"] == paper.cells["scan105"] == 0.76  # the paper's own figure
    assert rows["GCGS"]["cells"][tables.MEAN_DTU] == paper.cells[tables.MEAN_DTU]
    assert "no MVS + TSDF Chamfer" in Path("reports/table1.md").read_text()
