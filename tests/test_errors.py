"""Input errors share one base class; `gcgs` prints exactly those as one line and lets
everything else (bugs) keep its traceback."""
from __future__ import annotations

import subprocess
import sys

import pytest

from pipeline.cli import main
from pipeline.errors import InputError, MissingInputError


def test_every_input_error_class_derives_from_the_base():
    from pipeline.errors import ConfigError
    from pipeline.data.scene import SceneError
    from pipeline.evaluation.gt import GroundTruthError
    from pipeline.evaluation.sampling import MeshError
    from pipeline.geometry import CameraError
    from pipeline.init.io import InitFormatError
    from pipeline.meshing.tsdf import FusionError
    from pipeline.onnx_models import ModelError
    from pipeline.priors.features import FeatureError
    from pipeline.priors.io import PriorsFormatError
    from pipeline.priors.normals import NormalError

    for cls in (ConfigError, SceneError, GroundTruthError, MeshError, CameraError, InitFormatError, FusionError,
                ModelError, FeatureError, PriorsFormatError, NormalError, MissingInputError):
        assert issubclass(cls, InputError), cls
    assert issubclass(MissingInputError, FileNotFoundError)


def test_bad_input_is_one_line_naming_the_file(tmp_path, capsys):
    missing = tmp_path / "nope"
    assert main(["prepare", "--src", str(missing), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err
    assert err == f"gcgs prepare: error: {missing}: scene directory not found\n"


def test_bad_config_override_is_one_line(tmp_path, capsys):
    assert main(["tsdf", "--init-dir", str(tmp_path / "init"), "--scene", str(tmp_path / "scene"), "--out", str(tmp_path / "m.ply"),
                 "--voxel-norm", "0.02", "--trunc-norm", "0.01"]) == 1
    assert capsys.readouterr().err == "gcgs tsdf: error: mesh: need 0 < voxel_norm < trunc_norm, got 0.02, 0.01\n"


@pytest.mark.parametrize("exc", [ValueError("a bug"), OSError("a bug"), FileNotFoundError("a bug")])
def test_other_errors_keep_their_traceback(monkeypatch, exc):
    import pipeline.stages.params as stage

    def broken(args):
        raise exc

    monkeypatch.setattr(stage, "run", broken)
    with pytest.raises(type(exc), match="a bug"):
        main(["params"])


def test_a_bug_prints_a_traceback_from_the_command_line(tmp_path):
    """Through the real entry point: a programming error is not dressed up as bad input."""
    code = ("import sys, pipeline.stages.params as s, pipeline.cli as c\n"
            "s.run = lambda args: [][1]\n"
            "sys.exit(c.main(['params']))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 1
    assert "Traceback" in proc.stderr and "IndexError" in proc.stderr
