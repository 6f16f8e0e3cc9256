"""The priors stage end to end: real onnxruntime sessions on exported tiny models, the
default backends against ground truth, loss-weight gating, and clean failures."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from onnx_helpers import FakeVisMVSNet, export_fake_dsine, export_fake_vismvsnet
from relief_scene import write_relief_scene
from pipeline import cli
from pipeline.atomic import MARKER
from pipeline.config.params import PARAMS_PATH
from pipeline.data import dtu
from pipeline.priors.io import features_path, normals_path, read_features, read_normals

W, H = 80, 60
VIEWS = (23, 24, 33)


@pytest.fixture(scope="module")
def setup(tmp_path_factory, bundled_scan):
    """A rendered relief scene in the DTU layout, its ground-truth depth as the init
    output, and the two fake ONNX models."""
    root = tmp_path_factory.mktemp("priors")
    scene_dir, init_dir, sc = write_relief_scene(root, bundled_scan, VIEWS, W, H)
    return {
        "root": root, "scene": scene_dir, "init": init_dir, "gt": sc,
        "dsine": export_fake_dsine(root / "dsine.onnx"), "vis": export_fake_vismvsnet(root / "vis.onnx"),
    }


def params_file(tmp_path: Path, ablation_run=(), **loss) -> Path:
    params = yaml.safe_load(PARAMS_PATH.read_text())
    params["loss"].update(loss)
    params["ablation"]["run"] = list(ablation_run)
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump(params))
    return p


def run_cli(setup, out, *extra, params=None):
    args = ["priors", "--scene", str(setup["scene"]), "--init-dir", str(setup["init"]), "--out-dir", str(out)]
    if params is not None:
        args += ["--params", str(params)]
    return cli.main(args + list(extra))


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def test_default_backends_against_ground_truth(setup, tmp_path):
    out = tmp_path / "out"
    assert run_cli(setup, out) == 0
    gt = setup["gt"]
    for i, v in enumerate(VIEWS):
        n = read_normals(normals_path(out, v))
        assert n.backend == "default" and n.normal_cam.shape == (H, W, 3)
        hit = gt.depth_mm[i] > 0
        assert n.valid.sum() > 0.5 * hit.sum() and not n.valid[~hit].any()
        # Normals from (exact) depth vs the ray-cast face normals of the mesh.
        assert np.median(angle_deg(n.normal_cam[n.valid], gt.normal_cam[i][n.valid])) < 1.5
        f = read_features(features_path(out, v))
        assert f.features.shape == (50, H // 2, W // 2) and f.image_size == (H, W) and f.backend == "default"
    assert (out / "priors.json").is_file()


def test_onnx_backends_run_through_onnxruntime(setup, tmp_path):
    out = tmp_path / "out"
    rc = run_cli(setup, out, "--normals", "dsine", "--features", "vismvsnet",
                 "--dsine-model", str(setup["dsine"]), "--vismvsnet-model", str(setup["vis"]))
    assert rc == 0
    import torch

    from pipeline.priors.features import vismvsnet_input

    scene = dtu.load_scene(setup["scene"], view_ids=None)
    for i, v in enumerate(VIEWS):
        n = read_normals(normals_path(out, v))
        assert n.backend == "dsine" and n.valid.any()
        np.testing.assert_allclose(np.linalg.norm(n.normal_cam[n.valid], axis=-1), 1.0, atol=1e-5)
        f = read_features(features_path(out, v))
        assert f.backend == "vismvsnet" and f.features.shape == (32, H // 2, W // 2)
        want = FakeVisMVSNet()(torch.from_numpy(vismvsnet_input(scene.images[i]))).detach().numpy()[0]
        np.testing.assert_allclose(f.features, want, rtol=2e-3, atol=2e-3)  # stored as float16


@pytest.mark.parametrize(("loss", "has_normals", "has_features"), [
    ({"lambda_gcf": 0.0, "lambda_nor": 0.1}, True, False),
    ({"lambda_gcf": 2.0, "lambda_nor": 0.0}, False, True),
    ({"lambda_gcf": 0.0, "lambda_nor": 0.0}, False, False),
])
def test_zero_loss_weights_skip_work(setup, tmp_path, loss, has_normals, has_features):
    out = tmp_path / "out"
    # A missing init dir proves the default normals are not even looked at when unused.
    init = setup["init"] if has_normals else tmp_path / "no_init"
    args = ["priors", "--scene", str(setup["scene"]), "--init-dir", str(init), "--out-dir", str(out),
            "--params", str(params_file(tmp_path, **loss)), "--vismvsnet-model", str(tmp_path / "absent.onnx")]
    if has_features:
        args.remove("--vismvsnet-model")
        args.remove(str(tmp_path / "absent.onnx"))
    assert cli.main(args) == 0
    assert (out / "normals").is_dir() == has_normals
    assert (out / "features").is_dir() == has_features
    assert (out / "priors.json").is_file()


def test_a_prior_an_ablation_cell_weights_is_computed(setup, tmp_path):
    """The main loss weights neither prior, but cells of ablation.run train with L_gcf and
    with L_nor on the same priors folder: the features and normals are there for them."""
    out = tmp_path / "out"
    params = yaml.safe_load(params_file(tmp_path, lambda_gcf=0.0, lambda_nor=0.0).read_text())
    params["ablation"]["variants"]["with_gcf"] = {"loss": {"lambda_gcf": 2.0}}
    params["ablation"]["variants"]["with_nor"] = {"loss": {"lambda_nor": 0.25}}
    params["ablation"]["run"] = ["with_gcf", "with_nor"]
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    assert run_cli(setup, out, params=tmp_path / "params.yaml") == 0
    assert (out / "features").is_dir() and (out / "normals").is_dir()


def leftovers(parent: Path, name: str) -> list[Path]:
    return [p for p in parent.iterdir() if p.name.startswith(f".{name}.")]


def test_bad_models_and_scenes_fail_cleanly(setup, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("previous result")
    (out / MARKER).write_text('{"written_by": "gcgs", "kind": "priors"}')  # an earlier priors output
    bad = tmp_path / "broken.onnx"
    bad.write_bytes(b"\x08\x01garbage")
    assert run_cli(setup, out, "--features", "vismvsnet", "--vismvsnet-model", str(bad)) == 1
    assert "broken.onnx: not a loadable ONNX model" in capsys.readouterr().err
    # A model with the wrong contract (DSINE file given as the feature extractor).
    assert run_cli(setup, out, "--features", "vismvsnet", "--vismvsnet-model", str(setup["dsine"])) == 1
    assert "does not follow the vismvsnet_features contract" in capsys.readouterr().err
    assert run_cli(setup, out, "--normals", "dsine", "--dsine-model", str(tmp_path / "none.onnx")) == 1
    assert "none.onnx: dsine model file not found" in capsys.readouterr().err
    # Default normals without the init depth maps.
    assert cli.main(["priors", "--scene", str(setup["scene"]), "--init-dir", str(tmp_path / "noinit"),
                     "--out-dir", str(out)]) == 1
    assert "noinit/depth/023.npz: missing depth map for view 23" in capsys.readouterr().err
    assert cli.main(["priors", "--scene", str(tmp_path / "noscene"), "--out-dir", str(out)]) == 1
    assert "noscene: scene directory not found" in capsys.readouterr().err
    # The previous output is untouched and no temporary folder is left behind.
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "old.txt"]
    assert leftovers(tmp_path, "out") == []


def test_failure_mid_run_leaves_nothing(setup, tmp_path, capsys):
    """A model whose output is non-finite fails after the first outputs were written to
    the temporary folder; nothing must appear under the output path."""
    from onnx_helpers import NaNFeatures

    nan_model = export_fake_vismvsnet(tmp_path / "nan.onnx", NaNFeatures())
    out = tmp_path / "out"
    assert run_cli(setup, out, "--features", "vismvsnet", "--vismvsnet-model", str(nan_model)) == 1
    assert "output 'features' has non-finite values" in capsys.readouterr().err
    assert not out.exists() and leftovers(tmp_path, "out") == []


def test_dvc_stage_declares_what_it_reads():
    """The stage reruns on its inputs and its own params only: the loss weights that gate
    it, the priors section, the scene, the init output, models/ and its code."""
    stages = yaml.safe_load((PARAMS_PATH.parent / "dvc.yaml").read_text())["stages"]
    do = stages["priors"]["do"]
    assert stages["priors"]["foreach"] == "${scenes}"
    assert sorted(do["params"]) == ["ablation.run", "ablation.variants", "loss", "priors"]
    deps = set(do["deps"])

    def covered(path: str) -> bool:  # listed itself, or a listed folder holds it
        return path in deps or any(path.startswith(d.rstrip("/") + "/") for d in deps)

    for path in ("data/scenes/${key}", "data/init/${key}", "models", "src/pipeline/stages/priors.py",
                 "src/pipeline/runs/priors.py", "src/pipeline/priors/features.py", "src/pipeline/priors/normals.py",
                 "src/pipeline/priors/io.py", "src/pipeline/onnx_models.py"):
        assert covered(path), path
    assert do["outs"] == ["data/priors/${key}"]
    # Backends and model paths come from params.yaml, not from the command line.
    assert "--normals" not in do["cmd"] and "--features" not in do["cmd"] and "model" not in do["cmd"]
    assert (PARAMS_PATH.parent / "models").is_dir()  # a DVC dependency must exist
