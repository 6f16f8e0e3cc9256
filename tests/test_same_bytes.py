"""Same inputs, same bytes (issue 8): every data stage run twice on the same inputs writes
byte-identical outputs, so DVC's hashes (and a shared remote) work. Timings and machine
figures are printed, never written into stage outputs."""
from __future__ import annotations

import hashlib
import json
import shutil
import time
from pathlib import Path

import pytest
import yaml

from pipeline.cli import main
from pipeline.config.params import PARAMS_PATH

W, H = 80, 60


def tree_hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def run_twice(argv: list[str], out: Path, monkeypatch) -> dict[str, str]:
    """Run ``gcgs argv`` twice into ``out`` (the first result moved aside), the second
    time with the wall clock a day later; return the first run's hashes after checking
    that both runs wrote the same files with the same bytes."""
    assert main(argv) == 0
    first = tree_hashes(out)
    shutil.move(str(out), str(out.with_name(out.name + ".first")))
    later = time.time() + 86400.0
    with monkeypatch.context() as m:  # anything that writes the time now writes another one
        m.setattr(time, "time", lambda: later)
        m.setattr(time, "asctime", lambda *a: "Fri Jan  2 00:00:00 1970")
        m.setattr(time, "localtime", lambda *a: time.gmtime(later))
        assert main(argv) == 0
    second = tree_hashes(out)
    assert first.keys() == second.keys()
    differ = [k for k in first if first[k] != second[k]]
    assert not differ, f"{argv[0]}: files differ between two runs on the same inputs: {differ}"
    return first


@pytest.fixture()
def small_params(tmp_path) -> Path:
    params = yaml.safe_load(PARAMS_PATH.read_text())
    params["data"].update(width=W, height=H)
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    return path


def test_data_stages_give_the_same_bytes_twice(tmp_path, bundled_scan, small_params, monkeypatch):
    synth = tmp_path / "synth_relief"
    files = run_twice(["synth", "synth_relief", "--out", str(synth), "--width", str(W), "--height", str(H),
                       "--cameras", str(bundled_scan)], synth, monkeypatch)
    assert any(f.endswith(".mat") for f in files)  # the GT .mat files (scipy writes a timestamp)

    scene = tmp_path / "scene"
    run_twice(["prepare", "--src", str(synth), "--out", str(scene), "--params", str(small_params)], scene, monkeypatch)

    init = tmp_path / "init"
    files = run_twice(["init", "--scene", str(scene), "--out-dir", str(init), "--params", str(small_params)],
                      init, monkeypatch)
    assert "init.json" in files and "points.ply" in files
    facts = json.loads((init / "init.json").read_text())
    assert not {"time_s", "peak_rss_mb"} & set(facts)

    priors = tmp_path / "priors"
    files = run_twice(["priors", "--scene", str(scene), "--init-dir", str(init), "--out-dir", str(priors),
                       "--params", str(small_params)], priors, monkeypatch)
    assert any(f.startswith("normals") for f in files) and any(f.startswith("features") for f in files)
    facts = json.loads((priors / "priors.json").read_text())
    assert not {"time_s", "peak_rss_mb", "load_s", "normals_s", "features_s"} & set(facts)
