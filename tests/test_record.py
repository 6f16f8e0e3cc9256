"""The per-scene metrics record: written and read through one definition; a malformed file
or figure is an error naming the file and the field."""
from __future__ import annotations

import json
import math
import re

import pytest

from pipeline.errors import MissingInputError
from pipeline.evaluation.record import (Chamfer, HeldOut, MetricsError, SceneMetrics, distance_band_key,
                                        distance_band_lower_mm)

COMMON = {"scene": "s", "train": {"iterations": 5}, "timing": {"wall_s": 1.0}, "mesh": {"triangles_kept": 3}}


def _evaluate_mesh_result(**over):
    m = {"accuracy_mm": 0.5, "completeness_mm": 1.5, "overall_mm": 1.0, "valid": True, "problems": [],
         "counts": {"completeness_used": 30, "gt_above_plane": 40}, "timings_s": {}, "config": {},
         "accuracy_by_views_seen": {"2+": {"fraction": 0.9, "accuracy_mm": 0.4}, "1": {"fraction": 0.1, "accuracy_mm": 1.4},
                                    "0": {"fraction": 0.0, "accuracy_mm": math.nan}},
         "completeness_by_views_seen": {"2+": {"fraction": 0.6, "completeness_mm": 0.3},
                                        "1": {"fraction": 0.0, "completeness_mm": math.nan},
                                        "0": {"fraction": 0.4, "completeness_mm": 3.3}},
         "accuracy_by_distance": {"0-0.5": {"fraction": 0.8, "share_mm": 0.2}, "0.5-1": {"fraction": 0.2, "share_mm": 0.3}},
         "completeness_by_distance": {"0-0.5": {"fraction": 0.0, "share_mm": 0.0}, "0.5-20": {"fraction": 1.0, "share_mm": 1.5}}}
    return m | over


def test_round_trip_keeps_every_figure(tmp_path):
    m = SceneMetrics(**COMMON, chamfer=Chamfer.of(_evaluate_mesh_result()), variant={"name": "v"})
    m.write(tmp_path / "m.json")
    back = SceneMetrics.read(tmp_path / "m.json")
    assert back.chamfer.figures("x") == {"overall": 1.0, "accuracy": 0.5, "completeness": 1.5}
    assert back.chamfer.covered_fraction("x") == 0.75
    assert back.variant == {"name": "v"} and back.heldout is None
    # JSON has no NaN: an empty group's accuracy is null and reads back as NaN
    assert json.loads((tmp_path / "m.json").read_text())["chamfer"]["accuracy_by_views_seen"]["0"]["accuracy_mm"] is None
    assert back.chamfer.completeness_by_views_seen["0"] == {"fraction": 0.4, "completeness_mm": 3.3}
    assert math.isnan(back.chamfer.completeness_by_views_seen["1"]["completeness_mm"])
    assert back.chamfer.accuracy_by_distance == {"0-0.5": {"fraction": 0.8, "share_mm": 0.2},
                                                 "0.5-1": {"fraction": 0.2, "share_mm": 0.3}}
    assert back.chamfer.completeness_by_distance["0.5-20"] == {"fraction": 1.0, "share_mm": 1.5}
    h = SceneMetrics(**COMMON, heldout=HeldOut(4, (200, 150), 0.9, 0.7, None))
    h.write(tmp_path / "h.json")
    assert SceneMetrics.read(tmp_path / "h.json").heldout == h.heldout


def test_empty_group_survives_a_json_round_trip_of_the_evaluation():
    """The baseline stage reads evaluate_mesh's result back from its JSON file (an empty
    seen-group's accuracy is null there) and writes it again: null stays null."""
    from_file = json.loads(json.dumps(Chamfer.of(_evaluate_mesh_result()).to_json()))
    assert from_file["accuracy_by_views_seen"]["0"]["accuracy_mm"] is None
    again = Chamfer.of(from_file | {"timings_s": {}, "config": {}})
    assert math.isnan(again.accuracy_by_views_seen["0"]["accuracy_mm"])
    assert again.to_json() == from_file


def test_undefined_chamfer_is_written_as_null_and_refused_as_a_figure(tmp_path):
    bad = _evaluate_mesh_result(accuracy_mm=math.nan, overall_mm=math.nan, valid=False, problems=["no data point"])
    SceneMetrics(**COMMON, chamfer=Chamfer.of(bad)).write(tmp_path / "m.json")
    back = SceneMetrics.read(tmp_path / "m.json")
    assert not back.chamfer.valid and math.isnan(back.chamfer.overall_mm)
    with pytest.raises(MetricsError, match=r"here: Chamfer overall, accuracy undefined \(no data point\)"):
        back.chamfer.figures("here")


@pytest.mark.parametrize("content, message", [
    (None, r"m\.json: no metrics \(file not found; run it"),
    ("[1]", r"m\.json: metrics must be a JSON object, got list"),
    ("{", r"m\.json: metrics are not valid JSON"),
    (json.dumps({"scene": "s"}), r"m\.json: missing `train`, `timing`, `mesh`"),
    (json.dumps(COMMON), r"m\.json: exactly one of `chamfer`"),
    (json.dumps(COMMON | {"chamfer": {"accuracy_mm": "0.5", "valid": True}}),
     r"m\.json: chamfer: `accuracy_mm` must be a number, got '0\.5'"),
    (json.dumps(COMMON | {"heldout": {"views": 3, "iou_mean": 0.9}}), r"m\.json: heldout: `hull_iou_mean` must be"),
])
def test_bad_files_are_named(tmp_path, content, message):
    path = tmp_path / "m.json"
    if content is not None:
        path.write_text(content)
    with pytest.raises((MetricsError, MissingInputError), match=message):
        SceneMetrics.read(path, "run it")


def test_covered_fraction_needs_the_counts():
    c = Chamfer.of(_evaluate_mesh_result(counts={}))
    with pytest.raises(MetricsError, match=r"f: `completeness_used` must be a finite number"):
        c.covered_fraction("f")


def test_a_record_without_the_splits_reads_back_without_them(tmp_path):
    """Reports scored before a split existed (or of a real scan, with no views-seen split)
    have none of them: they read back as None and are written without the keys."""
    plain = {k: v for k, v in _evaluate_mesh_result().items() if "_by_" not in k}
    SceneMetrics(**COMMON, chamfer=Chamfer.of(plain)).write(tmp_path / "m.json")
    back = SceneMetrics.read(tmp_path / "m.json")
    assert back.chamfer.accuracy_by_distance is None and back.chamfer.completeness_by_views_seen is None
    assert not any("_by_" in k for k in json.loads((tmp_path / "m.json").read_text())["chamfer"])


def test_accuracy_beyond_sums_the_bands_from_a_lower_edge():
    c = Chamfer.of(_evaluate_mesh_result(accuracy_by_distance={
        distance_band_key(0, 0.5): {"fraction": 0.7, "share_mm": 0.1}, distance_band_key(0.5, 1): {"fraction": 0.2, "share_mm": 0.15},
        distance_band_key(1, 2): {"fraction": 0.06, "share_mm": 0.09}, distance_band_key(2, 20): {"fraction": 0.04, "share_mm": 0.3}}))
    assert c.accuracy_beyond(1.0) == pytest.approx((0.39, 0.10))
    assert c.accuracy_beyond(0.0) == pytest.approx((0.64, 1.0))
    assert all(math.isnan(x) for x in c.accuracy_beyond(50.0))
    assert all(math.isnan(x) for x in Chamfer.of(_evaluate_mesh_result(accuracy_by_distance=None)).accuracy_beyond(1.0))


@pytest.mark.parametrize("key", ["1", "a-2", "1-b", ""])
def test_malformed_distance_band_is_named(key):
    with pytest.raises(MetricsError, match=re.escape(repr(key))):
        distance_band_lower_mm(key)
