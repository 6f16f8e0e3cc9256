"""Config values are checked when they are loaded (issue 57, "no silent wrong inputs"):
learning rates and other ranges, value types, Hydra compositions and params files, the
input views `gcgs evaluate` culls with, and the sphere `gcgs prepare` accepts. Each bad
value is one ConfigError (or SceneError) line naming the key or file, and nothing is written."""
from __future__ import annotations

import json
import re

import pytest
import yaml

from pipeline.cli import main
from pipeline.config.data import DataConfig
from pipeline.config.init import InitConfig
from pipeline.config.loss import LossConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import CONF_DIR, PARAMS_PATH, compose_params, load_params, section
from pipeline.config.priors import PriorsConfig
from pipeline.config.synth import SynthConfig
from pipeline.config.variants import variant_configs
from pipeline.errors import ConfigError

PARAMS = load_params(PARAMS_PATH)


def params_file(tmp_path, change, name="params.yaml"):
    """A copy of the committed params with ``change(params)`` applied."""
    params = yaml.safe_load(PARAMS_PATH.read_text())
    change(params)
    path = tmp_path / name
    path.write_text(yaml.safe_dump(params))
    return path


def one_line_error(capsys, command: str) -> str:
    """The single stderr line of a refused command (no traceback, nothing on stdout)."""
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err and captured.err.count("\n") == 1, captured.err
    assert captured.err.startswith(f"gcgs {command}: error: ")
    return captured.err


# --- 1. learning rates ------------------------------------------------------------------------


@pytest.mark.parametrize("key", ["means", "means_final", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest"])
def test_negative_learning_rate_is_named(key):
    with pytest.raises(ConfigError, match=rf"^optimize\.lr\.{key} must be "):
        section(OptimizeConfig, "optimize", PARAMS, {f"lr.{key}": -0.05})


def test_learning_rates_zero_freezes_but_the_decaying_means_rate_must_be_positive():
    cfg = section(OptimizeConfig, "optimize", PARAMS, {"lr.opacity_logits": 0.0, "lr.sh_rest": 0})
    assert (cfg.lr.opacity_logits, cfg.lr.sh_rest) == (0.0, 0)
    for key in ("means", "means_final"):  # exp of interpolated logs: log(0) is a math domain error
        with pytest.raises(ConfigError, match=rf"optimize\.lr\.{key} must be > 0, got 0"):
            section(OptimizeConfig, "optimize", PARAMS, {f"lr.{key}": 0.0})


def test_a_variants_bad_learning_rate_names_the_variant():
    params = json.loads(json.dumps(PARAMS))
    params["ablation"]["variants"]["sa_it1000"]["optimize"]["lr"]["means"] = -1.13e-4
    with pytest.raises(ConfigError, match=r"^optimize\.lr\.means must be > 0, got -0\.000113 "
                                          r"\(with ablation\.variants\.sa_it1000\.optimize merged in\)$"):
        variant_configs(params, "sa_it1000")


def test_cli_negative_learning_rate_is_one_line_and_trains_nothing(tmp_path, capsys, bundled_scan):
    bad = params_file(tmp_path, lambda p: p["optimize"]["lr"].update(opacity_logits=-0.05))
    out = tmp_path / "surfels"
    assert main(["optimize", "--scene", str(bundled_scan), "--init-dir", str(tmp_path / "init"),
                 "--priors-dir", str(tmp_path / "priors"), "--out-dir", str(out), "--params", str(bad)]) == 1
    assert one_line_error(capsys, "optimize") == \
        "gcgs optimize: error: optimize.lr.opacity_logits must be >= 0, got -0.05\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml"]


# --- 2. types and ranges ------------------------------------------------------------------------


@pytest.mark.parametrize("cls, key, field, value, message", [
    (OptimizeConfig, "optimize", "iterations", 1.5, "optimize.iterations must be an integer, got 1.5"),
    (OptimizeConfig, "optimize", "iterations", "abc", "optimize.iterations must be an integer, got 'abc'"),
    (OptimizeConfig, "optimize", "iterations", True, "optimize.iterations must be an integer, got True"),
    (OptimizeConfig, "optimize", "densify.every", 100.5, "optimize.densify.every must be an integer, got 100.5"),
    (OptimizeConfig, "optimize", "init_normals", "yes", "optimize.init_normals must be true or false, got 'yes'"),
    (OptimizeConfig, "optimize", "masks", 1, "optimize.masks must be a string, got 1"),
    (OptimizeConfig, "optimize", "lr", 3, "optimize.lr must be a section"),
    (OptimizeConfig, "optimize", "downscale", [[0.0, "x"]], r"optimize.downscale\[0\]\[1\] must be a number, got 'x'"),
    (DataConfig, "data", "width", "abc", "data.width must be an integer, got 'abc'"),
    (DataConfig, "data", "views", [23, "24"], r"data.views\[1\] must be an integer, got '24'"),
    (DataConfig, "data", "views", 23, "data.views must be a list, got 23"),
    (LossConfig, "loss", "lambda_gcf", True, "loss.lambda_gcf must be a number, got True"),
    (LossConfig, "loss", "lambda_gcf", "2", "loss.lambda_gcf must be a number, got '2'"),
    (InitConfig, "init", "mast3r.model", 3, "init.mast3r.model must be a string or null, got 3"),
    (PriorsConfig, "priors", "feature_scales", [1, 2.0], r"priors.feature_scales\[1\] must be an integer, got 2.0"),
])
def test_wrong_type_is_named(cls, key, field, value, message):
    with pytest.raises(ConfigError, match=f"^{message}"):
        section(cls, key, PARAMS, {field: value})


@pytest.mark.parametrize("cls, key, field, value, message", [
    (OptimizeConfig, "optimize", "iterations", 0, "optimize.iterations must be >= 1, got 0"),
    (OptimizeConfig, "optimize", "adam_betas", [0.9, 1.0], r"optimize.adam_betas must be \[beta1, beta2\], each in \[0, 1\), got \[0.9, 1.0\]"),
    (OptimizeConfig, "optimize", "adam_betas", [0.9], r"optimize.adam_betas must be \[beta1, beta2\], each in \[0, 1\), got \[0.9\]"),
    (OptimizeConfig, "optimize", "seed", -1, "optimize.seed must be >= 0, got -1"),
    (OptimizeConfig, "optimize", "scene_extent", 0.0, "optimize.scene_extent must be > 0, got 0.0"),
    (OptimizeConfig, "optimize", "background", 1.5, r"optimize.background must be in \[0, 1\], got 1.5"),
    (OptimizeConfig, "optimize", "start.d", -1, "optimize.start.d must be >= 0, got -1"),
    (DataConfig, "data", "width", 0, "data.width, data.height: image size must be positive"),
    (SynthConfig, "synth", "height", -600, "synth.width, synth.height: image size must be positive"),
    (LossConfig, "loss", "lambda_d", -1.0, "loss.lambda_d must be >= 0, got -1.0"),
    (LossConfig, "loss", "lambda_mask", float("nan"), "loss.lambda_mask must be a finite number >= 0, got nan"),
    (LossConfig, "loss", "lambda_dssim", 1.2, r"loss.lambda_dssim must be in \[0, 1\], got 1.2"),
    (InitConfig, "init", "voxel_norm", -0.002, "init.voxel_norm must be >= 0, got -0.002"),
    (InitConfig, "init", "sfm.ratio", 0.0, "init.sfm.ratio must be > 0, got 0.0"),
    (InitConfig, "init", "consistency.px", -1.0, "init.consistency.px must be > 0, got -1.0"),
    (MeshConfig, "mesh", "voxel_norm", 0.0, "mesh: need 0 < voxel_norm < trunc_norm"),
])
def test_value_out_of_range_is_named(cls, key, field, value, message):
    with pytest.raises(ConfigError, match=f"^{message}"):
        section(cls, key, PARAMS, {field: value})


def test_accepted_values_are_kept_as_given():
    """An int where a float is expected is a number, kept as it is (nothing is converted);
    None where a value is optional."""
    loss = section(LossConfig, "loss", PARAMS, {"lambda_gcf": 2})
    assert loss.lambda_gcf == 2 and type(loss.lambda_gcf) is int
    init = {**PARAMS["init"], "mast3r": {**PARAMS["init"]["mast3r"], "model": None}}
    assert section(InitConfig, "init", {"init": init}).mast3r.model is None


@pytest.mark.parametrize("command, change, message", [
    ("optimize", lambda p: p["optimize"].update(iterations=1.5), "optimize.iterations must be an integer, got 1.5"),
    ("prepare", lambda p: p["data"].update(width="abc"), "data.width must be an integer, got 'abc'"),
])
def test_cli_wrong_type_is_one_line_and_writes_nothing(tmp_path, capsys, bundled_scan, command, change, message):
    bad = params_file(tmp_path, change)
    out = tmp_path / "out"
    if command == "optimize":
        args = ["--scene", str(bundled_scan), "--init-dir", str(tmp_path / "init"), "--priors-dir",
                str(tmp_path / "priors"), "--out-dir", str(out)]
    else:
        args = ["--src", str(bundled_scan), "--out", str(out)]
    assert main([command, *args, "--params", str(bad)]) == 1
    assert one_line_error(capsys, command) == f"gcgs {command}: error: {message}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["params.yaml"]


# --- 3. Hydra compositions and params files -----------------------------------------------------


def test_missing_preset_names_the_group_and_its_choices():
    choices = sorted(p.stem for p in (CONF_DIR / "optimize").glob("*.yaml"))
    assert len(choices) > 1
    with pytest.raises(ConfigError) as err:
        compose_params(["optimize=nonexistent"])
    assert str(err.value) == f"optimize=nonexistent: no preset 'nonexistent' in conf/optimize; choices: {', '.join(choices)}"


@pytest.mark.parametrize("override, message", [
    ("optimze=fast", "optimze=fast: no config group or key 'optimze'; groups: ablation, data, evaluate, init, loss, "
                     "mesh, optimize, priors, synth"),
    ("optimize.nokey=1", "optimize.nokey=1: unknown key optimize.nokey (conf/ has no such setting)"),
    ("foo", "override 'foo': missing EQUAL at '<EOF>' (the form is KEY=VALUE)"),
    ("optimize.iterations=${nope}", "optimize.iterations: Interpolation key 'nope' not found"),
])
def test_composition_error_is_one_line_naming_the_override(override, message):
    with pytest.raises(ConfigError) as err:
        compose_params([override])
    assert str(err.value) == message


@pytest.mark.parametrize("override, message", [
    ("optimize=nonexistent", "optimize=nonexistent: no preset 'nonexistent' in conf/optimize; choices: "),
    ("optimize.lr.means=-1", "optimize.lr.means must be > 0, got -1"),
    ("optimize.iterations=abc", "optimize.iterations must be an integer, got 'abc'"),
    ("+optimise.iterations=3", "unknown top-level key(s) ['optimise']"),
])
def test_cli_params_refuses_without_writing(tmp_path, capsys, monkeypatch, override, message):
    import pipeline.stages.params as stage

    target = tmp_path / "params.yaml"
    monkeypatch.setattr(stage, "PARAMS_PATH", target)
    assert main(["params", "--write", override]) == 1
    assert one_line_error(capsys, "params").startswith(f"gcgs params: error: {message}")
    assert not target.exists()


@pytest.mark.parametrize("text, message", [
    ("data: [1, 2\noptimize: {}\n", "not valid YAML (expected ',' or ']', but got ':' at line 2, column 9)"),
    ("- data\n- optimize\n", "a params file must map section names to sections, got a list"),
    ("just a string\n", "a params file must map section names to sections, got a str"),
])
def test_bad_params_file_is_named(tmp_path, capsys, bundled_scan, text, message):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    with pytest.raises(ConfigError, match=f"^{re.escape(f'{bad}: {message}')}$"):
        load_params(bad)
    out = tmp_path / "scene"
    assert main(["prepare", "--src", str(bundled_scan), "--out", str(out), "--params", str(bad)]) == 1
    assert one_line_error(capsys, "prepare") == f"gcgs prepare: error: {bad}: {message}\n"
    assert not out.exists()


def test_a_section_that_is_not_a_mapping_is_named():
    with pytest.raises(ConfigError, match=r"^optimize must be a section \(a mapping of keys to values\), got 3"):
        section(OptimizeConfig, "optimize", {"optimize": 3})


# --- every preset and variant still loads --------------------------------------------------------


@pytest.mark.parametrize("group, preset", [(d.name, p.stem) for d in sorted(CONF_DIR.iterdir())
                                           if d.is_dir() and d.name != "hydra" for p in sorted(d.glob("*.yaml"))])
def test_every_conf_preset_composes_into_valid_configs(group, preset):
    from pipeline.stages.params import check_params

    check_params(compose_params([f"{group}={preset}"]))


def test_the_committed_params_and_every_ablation_variant_validate():
    from pipeline.stages.params import check_params

    check_params(PARAMS)
    assert len(PARAMS["ablation"]["variants"]) > 10
    for name in PARAMS["ablation"]["variants"]:
        variant_configs(PARAMS, name)


# --- 4. gcgs evaluate culls with the scene's own input views -------------------------------------


def _scene_with_views(tmp_path, views):
    from test_evaluation import sphere, write_synthetic_scene

    from pipeline.evaluation import gt as gtmod

    V, F, _ = sphere(resolution=16)
    scene = tmp_path / "scene"
    write_synthetic_scene(scene, V, F)  # views 0, 1, 2; params data.views (23 24 33) are not among them
    meta = json.loads((scene / "scene.json").read_text())
    (scene / "scene.json").write_text(json.dumps({**meta, "views": views}))
    gtmod.write_ply_mesh(tmp_path / "mesh.ply", V, F)
    return scene


def test_evaluate_culls_with_the_views_the_scene_was_prepared_with(tmp_path, capsys):
    scene = _scene_with_views(tmp_path, [0, 2])
    args = ["evaluate", "--mesh", str(tmp_path / "mesh.ply"), "--scene", str(scene), "--cull", "input"]
    assert main([*args, "--out", str(tmp_path / "a.json")]) == 0
    assert json.loads((tmp_path / "a.json").read_text())["config"]["cull_view_ids"] == [0, 2]
    assert main([*args, "--views", "1", "--out", str(tmp_path / "b.json")]) == 0  # an explicit override
    assert json.loads((tmp_path / "b.json").read_text())["config"]["cull_view_ids"] == [1]


def test_evaluate_refuses_a_bad_views_record(tmp_path, capsys):
    scene = _scene_with_views(tmp_path, "0 2")
    out = tmp_path / "m.json"
    assert main(["evaluate", "--mesh", str(tmp_path / "mesh.ply"), "--scene", str(scene), "--out", str(out)]) == 1
    assert one_line_error(capsys, "evaluate") == \
        f"gcgs evaluate: error: {scene / 'scene.json'}: views must be a list of view ids, got '0 2'\n"
    assert not out.exists()


# --- 5. gcgs prepare refuses a sphere that init would refuse -------------------------------------


def test_prepare_refuses_a_sphere_the_camera_reader_refuses(tmp_path, capsys, bundled_scan):
    from pipeline.data import dtu
    from pipeline.data.capture import sphere_matrix

    out = tmp_path / "scene"
    assert main(["prepare", "--src", str(bundled_scan), "--out", str(out), "--width", "160",
                 "--sphere", "0", "0", "0", "1e-9"]) == 1
    assert one_line_error(capsys, "prepare") == (
        f"gcgs prepare: error: {bundled_scan}: the given sphere [0.0, 0.0, 0.0, 1e-09] makes a scale_mat that is "
        "singular, which gcgs init would refuse; give the radius in the input's world units\n")
    assert not out.exists()
    assert dtu.scale_mat_problem(sphere_matrix([0.0, 0.0, 0.0], 1e-9)) == "is singular"  # the reader's rule
    # A sphere it accepts is one the reader (so init) accepts.
    assert main(["prepare", "--src", str(bundled_scan), "--out", str(out), "--width", "160",
                 "--sphere", "0", "0", "0", "1e-3"]) == 0
    assert dtu.load_cameras(out).norm_to_world[0, 0] == 1e-3
