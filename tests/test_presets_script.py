"""scripts/presets.py: a ladder run from another folder scores against the ground truth of the
checkout whose data/ it reads."""
from __future__ import annotations

import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location("presets", Path(__file__).resolve().parents[1] / "scripts" / "presets.py")
presets = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(presets)


def test_scene_paths_resolve_against_the_inputs_checkout(tmp_path):
    params = {"optimize": {"seed": 0}, "scenes": {
        "synth_thin": {"src": "data/synth/synth_thin", "gt": "data/synth/synth_thin/gt"},
        "scan24": {"src": "/abs/scan24", "gt": None},
    }}
    got = presets.with_inputs(params, tmp_path / "data")
    assert got["scenes"]["synth_thin"] == {"src": str(tmp_path / "data/synth/synth_thin"),
                                           "gt": str(tmp_path / "data/synth/synth_thin/gt")}
    assert got["scenes"]["scan24"] == {"src": "/abs/scan24", "gt": None}
    assert got["optimize"] == params["optimize"]
    assert params["scenes"]["synth_thin"]["gt"] == "data/synth/synth_thin/gt", "the caller's params stay as they were"
