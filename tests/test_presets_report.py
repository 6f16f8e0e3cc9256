"""reports/presets.{csv,md,png}: the ladder's summary against a per-row recomputation, the
rise check, the CSV round trip and refusals (pipeline.reports.presets)."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.reports.presets import COLUMNS, markdown, read_rows, rises, summarize, write_report


def _rows(means: dict[str, float], scenes=("a", "b"), seeds=(0, 1, 2), seed_step=0.004) -> list[dict]:
    rng = np.random.default_rng(0)
    rows = []
    for (preset, mean), scene, seed in itertools.product(means.items(), scenes, seeds):
        ov = mean + (0.1 if scene == "b" else 0.0) + seed_step * seed
        rows.append({"preset": preset, "scene": scene, "seed": seed, "overall_mm": ov,
                     "accuracy_mm": ov / 3, "completeness_mm": ov * 5 / 3,
                     "train_wall_s": float(rng.uniform(10, 100)), "train_cpu_s": float(rng.uniform(10, 100)),
                     "peak_rss_mb": float(rng.uniform(500, 900)), "commit": "abc1234"})
    return rows


def test_summary_is_the_mean_of_scene_means_with_half_ranges():
    rows = _rows({"fast": 1.4, "long": 1.37})
    rows = [r for r in rows if not (r["preset"] == "long" and r["scene"] == "a" and r["seed"] == 2)]  # 2 seeds on a
    fast, long_ = summarize(rows)
    assert (fast.preset, long_.preset, long_.seeds) == ("fast", "long", 2)
    for s in (fast, long_):
        rs = [r for r in rows if r["preset"] == s.preset]
        for key in ("overall_mm", "accuracy_mm", "completeness_mm", "train_cpu_s", "train_wall_s"):
            per_scene = []
            for scene in ("a", "b"):
                v = [r[key] for r in rs if r["scene"] == scene]
                per_scene.append(sum(v) / len(v))
            assert getattr(s, key) == pytest.approx(sum(per_scene) / 2)
        for scene in ("a", "b"):
            v = [r["overall_mm"] for r in rs if r["scene"] == scene]
            assert s.overall_by_scene[scene] == pytest.approx(((sum(v) / len(v)), (max(v) - min(v)) / 2))
        assert s.peak_rss_mb == max(r["peak_rss_mb"] for r in rs)


def test_rises_flags_only_steps_beyond_the_tolerance_in_ladder_order():
    # Given out of order on purpose: the ladder's order decides the steps.
    rows = _rows({"paper": 1.395, "quick": 1.5, "long": 1.37, "fast": 1.40, "balanced": 1.375})
    summaries = summarize(rows)
    assert [s.preset for s in summaries] == ["quick", "fast", "balanced", "long", "paper"]
    found = rises(summaries)
    assert [(a, b) for a, b, _ in found] == [("long", "paper")]
    assert found[0][2] == pytest.approx(0.025)
    assert rises(summarize(_rows({"fast": 1.40, "balanced": 1.409}))) == []  # within 0.01 mm


def test_rises_refuses_presets_on_different_scenes():
    rows = _rows({"fast": 1.4}) + _rows({"long": 1.3}, scenes=("a",))
    with pytest.raises(InputError, match="different scenes"):
        rises(summarize(rows))


def test_report_round_trip_and_markdown(tmp_path):
    rows = _rows({"fast": 1.40, "long": 1.42})
    write_report(rows, tmp_path / "p.csv", tmp_path / "p.md", tmp_path / "p.png")
    back = read_rows(tmp_path / "p.csv")
    key = lambda r: (r["preset"], r["scene"], r["seed"])  # noqa: E731
    assert sorted(back, key=key) == sorted(rows, key=key)
    md = (tmp_path / "p.md").read_text()
    assert "`long` is 0.020 mm above `fast`" in md
    assert (tmp_path / "p.png").stat().st_size > 0


def test_markdown_leaves_a_partly_run_preset_out_of_the_check():
    rows = _rows({"fast": 1.40, "long": 1.38}) + _rows({"paper": 1.50}, scenes=("a",), seeds=(0,))
    md = markdown(summarize(rows), ["abc1234"])
    assert "More time never bought a worse mean surface" in md  # paper (one scene, one seed) not compared
    assert "Not compared (fewer scenes or seeds than `fast`): `paper`." in md


def test_read_rows_refuses_other_columns_and_bad_numbers(tmp_path):
    p = tmp_path / "p.csv"
    p.write_text("preset,scene\nfast,a\n")
    with pytest.raises(InputError, match="p.csv: columns"):
        read_rows(p)
    p.write_text(",".join(COLUMNS) + "\nfast,a,0,x,1,1,1,1,1,abc\n")
    with pytest.raises(InputError, match="p.csv: line 2"):
        read_rows(p)
    with pytest.raises(InputError, match="no measured run"):
        write_report([], tmp_path / "q.csv", tmp_path / "q.md", tmp_path / "q.png")
