"""The optimize and mesh stage commands on a tiny scene written to disk: outputs in the
documented layout, identical bytes from two runs (DVC hashes), timings only in the
metrics file, an interrupted run's checkpoint resumed, bad input named."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
import yaml

from optimize_scene import interrupt_training_at, write_stage_inputs
from pipeline import cli
from pipeline.atomic import MARKER



@pytest.fixture(scope="module")
def stage_inputs(tmp_path_factory):
    return write_stage_inputs(tmp_path_factory.mktemp("stage"))


def _optimize(root: Path, priors: Path, out: str, *extra: str) -> int:
    return cli.main(["optimize", "--scene", str(root / "scene"), "--init-dir", str(root / "init"), "--priors-dir",
                     str(priors), "--out-dir", str(root / out), "--checkpoint", str(root / f"{out}.pt"),
                     "--metrics", str(root / f"{out}_timing.json"), "--live-dir", str(root / f"{out}_live"),
                     "--no-progress", "--params", str(root / "params.yaml"), *extra])


def _digest(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def test_two_runs_give_identical_bytes_and_a_mesh(stage_inputs):
    root, priors = stage_inputs
    assert _optimize(root, priors, "a") == 0 and _optimize(root, priors, "b") == 0
    assert _digest(root / "a") == _digest(root / "b")
    assert sorted(p.name for p in (root / "a").iterdir()) == [MARKER, "splats_3dgs.ply", "surfels.ply", "train.json"]
    train = json.loads((root / "a" / "train.json").read_text())
    assert train["iterations"] == 10 and train["surfels_final"] > 0 and "wall_s" not in json.dumps(train)
    timing = json.loads((root / "a_timing.json").read_text())
    assert timing["wall_s"] > 0 and set(timing["split_s"]) >= {"render", "backward", "gcf", "nor"}
    assert not (root / "a.pt").exists()  # finished: no checkpoint left behind
    assert (root / "a_live" / "plots" / "metrics" / "train" / "total.tsv").is_file()
    assert cli.main(["mesh", "--scene", str(root / "scene"), "--surfels-dir", str(root / "a"), "--out-dir",
                     str(root / "mesh"), "--params", str(root / "params.yaml")]) == 0
    facts = json.loads((root / "mesh" / "mesh.json").read_text())
    assert facts["triangles_kept"] > 0 and (root / "mesh" / "mesh.ply").stat().st_size > 0


def test_a_missing_init_cloud_is_named(stage_inputs, tmp_path, capsys):
    root, priors = stage_inputs
    (tmp_path / "no_init").mkdir()
    rc = cli.main(["optimize", "--scene", str(root / "scene"), "--init-dir", str(tmp_path / "no_init"), "--priors-dir",
                   str(priors), "--out-dir", str(tmp_path / "out"), "--params", str(root / "params.yaml"),
                   "--checkpoint", str(tmp_path / "c.pt"), "--metrics", str(tmp_path / "m.json"),
                   "--live-dir", str(tmp_path / "live"), "--no-progress"])
    assert rc == 1 and "points.ply" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_missing_priors_are_named(stage_inputs, tmp_path, capsys):
    root, _ = stage_inputs
    (tmp_path / "no_priors").mkdir()
    params = yaml.safe_load((root / "params.yaml").read_text())
    params["loss"]["lambda_nor"] = 0.25  # a loss that reads the normal prior (off by default)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    rc = cli.main(["optimize", "--scene", str(root / "scene"), "--init-dir", str(root / "init"), "--priors-dir",
                   str(tmp_path / "no_priors"), "--out-dir", str(tmp_path / "out"), "--params", str(tmp_path / "params.yaml"),
                   "--checkpoint", str(tmp_path / "c.pt"), "--metrics", str(tmp_path / "m.json"),
                   "--live-dir", str(tmp_path / "live"), "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 1 and "missing" in err and "prior" in err
    assert not (tmp_path / "out").exists()


def test_ctrl_c_is_one_line_naming_the_checkpoint_and_the_rerun_resumes(stage_inputs, capsys, monkeypatch):
    root, priors = stage_inputs
    resume = interrupt_training_at(monkeypatch, 6)
    assert _optimize(root, priors, "ctrl_c") == 130
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert f"checkpoint {root / 'ctrl_c.pt'} (iteration 4) resumes it: rerun the same command" in lines[0]
    assert not (root / "ctrl_c").exists() and (root / "ctrl_c.pt").is_file()
    resume()
    assert _optimize(root, priors, "ctrl_c") == 0
    assert json.loads((root / "ctrl_c_timing.json").read_text())["resumed_from"] == 4
    assert _optimize(root, priors, "uninterrupted") == 0
    assert _digest(root / "ctrl_c") == _digest(root / "uninterrupted")


def test_sigterm_keeps_the_checkpoint_and_names_it_as_ctrl_c_does(stage_inputs, tmp_path):
    """SIGTERM (SLURM, ``docker stop``, ``timeout``) in the middle of a training: exit 130,
    one line naming the checkpoint and how to resume, the checkpoint kept, no output."""
    import os
    import signal
    import subprocess
    import sys
    import time

    root, priors = stage_inputs
    params = yaml.safe_load((root / "params.yaml").read_text())
    params["optimize"].update(iterations=100000, checkpoint_every=2)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    ckpt = tmp_path / "run.pt"
    cmd = [sys.executable, "-m", "pipeline.cli", "optimize", "--scene", str(root / "scene"), "--init-dir",
           str(root / "init"), "--priors-dir", str(priors), "--out-dir", str(tmp_path / "out"), "--checkpoint",
           str(ckpt), "--metrics", str(tmp_path / "timing.json"), "--live-dir", str(tmp_path / "live"),
           "--no-progress", "--params", str(tmp_path / "params.yaml")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "GCGS_THREADS": "1"})
    deadline = time.monotonic() + 300
    while not ckpt.is_file() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert ckpt.is_file(), proc.communicate()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert proc.returncode == 130, err
    assert len(lines) == 1 and f"the checkpoint {ckpt}" in lines[0] and "rerun the same command" in lines[0], err
    assert ckpt.is_file() and not (tmp_path / "out").exists()
