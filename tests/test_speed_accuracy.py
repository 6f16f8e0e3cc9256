"""The speed-accuracy report: the Pareto front against a brute-force definition, the
table and plot from per-cell reports, and bad reports named."""
import csv
import json

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.reports.speed_accuracy import collect_cells, pareto_front, write_report


def _dominated(i, t, e):
    return any(t[j] <= t[i] and e[j] <= e[i] and (t[j] < t[i] or e[j] < e[i]) for j in range(len(t)) if j != i)


@pytest.mark.parametrize("seed", range(5))
def test_pareto_front_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    t = rng.integers(1, 6, 25).astype(float)  # ties on purpose
    e = rng.integers(1, 6, 25).astype(float)
    front = pareto_front(t, e)
    assert front.tolist() == [not _dominated(i, t, e) for i in range(len(t))]
    assert front.any()


def test_identical_cells_are_both_on_the_front():
    assert pareto_front([1.0, 1.0, 2.0], [3.0, 3.0, 4.0]).tolist() == [True, True, False]


def _report(folder, scene, cell, overall, cpu):
    m = {"scene": scene, "mesh": {},
         "chamfer": {"overall_mm": overall, "accuracy_mm": overall / 2, "completeness_mm": overall * 1.5},
         "timing": {"wall_s": cpu / 2, "cpu_s": cpu, "peak_rss_mb": 100.0},
         "train": {"iterations": 10, "surfels_final": 5},
         "variant": {"name": cell, "init": "mvs", "optimize": {"iterations": 10}, "loss": {}, "mesh": {}},
         "provenance": {"load_average_1min": 1.0, "commit": "abc"}}
    (folder / scene).mkdir(parents=True, exist_ok=True)
    (folder / scene / f"{cell}.json").write_text(json.dumps(m))


def test_table_and_plot_from_cell_reports(tmp_path):
    for cell, overall, cpu in (("fast", 2.0, 10.0), ("slow", 1.0, 100.0), ("bad", 3.0, 50.0)):
        _report(tmp_path / "cells", "s", cell, overall, cpu)
    rows = collect_cells(tmp_path / "cells", ["s"], ["fast", "slow", "bad", "not_run"])
    assert [r["cell"] for r in rows] == ["fast", "slow", "bad"]
    assert [r["pareto"] for r in rows] == [True, True, False]
    write_report(rows, tmp_path / "sa.csv", tmp_path / "sa.png", labels={"fast": "fast"})
    with open(tmp_path / "sa.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [float(r["overall_mm"]) for r in table] == [2.0, 1.0, 3.0]
    assert table[0]["changes"] == json.dumps({"optimize": {"iterations": 10}})
    assert (tmp_path / "sa.png").read_bytes()[:4] == b"\x89PNG"


def test_bad_cell_report_is_named(tmp_path):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "x.json").write_text('{"chamfer": {}}')
    with pytest.raises(InputError, match=r"x\.json: missing `scene`, `train`, `timing`, `mesh`"):
        collect_cells(tmp_path, ["s"], ["x"])
    _report(tmp_path, "s", "y", 1.0, 1.0)
    m = json.loads((tmp_path / "s" / "y.json").read_text())
    del m["variant"]
    (tmp_path / "s" / "y.json").write_text(json.dumps(m))
    with pytest.raises(InputError, match=r"y\.json: not a variant report"):
        collect_cells(tmp_path, ["s"], ["y"])
    with pytest.raises(InputError, match="no measured cell"):
        write_report([], tmp_path / "a.csv", tmp_path / "a.png")
