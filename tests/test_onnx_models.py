"""ONNX contract checks, on real models exported from tiny torch modules."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from onnx_helpers import FakeVisMVSNet, NaNFeatures, WrongNames, export, export_fake_dsine, export_fake_vismvsnet
from pipeline.onnx_models import (
    DSINE_CONTRACT,
    VISMVSNET_FEATURES_CONTRACT,
    ModelContract,
    ModelError,
    TensorSpec,
    load_onnx,
)


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    d = tmp_path_factory.mktemp("onnx")
    return {
        "dsine": export_fake_dsine(d / "dsine.onnx"),
        "vis": export_fake_vismvsnet(d / "vis.onnx"),
        "dir": d,
    }


def test_valid_models_load_and_run(models):
    m = load_onnx(models["vis"], VISMVSNET_FEATURES_CONTRACT)
    assert "CPUExecutionProvider" in m.providers
    x = np.random.default_rng(0).standard_normal((1, 3, 32, 48)).astype(np.float32)
    out = m.run(image=x)["features"]
    ref = FakeVisMVSNet()(torch.from_numpy(x)).detach().numpy()
    assert out.shape == (1, 32, 16, 24)
    np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-4)

    d = load_onnx(models["dsine"], DSINE_CONTRACT)
    K = np.array([[[50.0, 0, 47.5], [0, 50.0, 31.5], [0, 0, 1]]], np.float32)
    n = d.run(image=np.zeros((1, 3, 64, 96), np.float32), intrinsics=K)["normal"]
    assert n.shape == (1, 3, 64, 96)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)


def test_missing_and_corrupt_files_name_the_file(models, tmp_path):
    with pytest.raises(ModelError, match=r"nope\.onnx: .*not found"):
        load_onnx(tmp_path / "nope.onnx", DSINE_CONTRACT)
    bad = tmp_path / "garbage.onnx"
    bad.write_bytes(b"this is not a protobuf" * 10)
    with pytest.raises(ModelError, match=r"garbage\.onnx: not a loadable ONNX model"):
        load_onnx(bad, DSINE_CONTRACT)
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(models["vis"].read_bytes()[:200])
    with pytest.raises(ModelError, match=r"truncated\.onnx"):
        load_onnx(truncated, VISMVSNET_FEATURES_CONTRACT)


def test_contract_mismatches_are_named(models, tmp_path):
    # A features model given as DSINE: input 'intrinsics' and output 'normal' are missing.
    with pytest.raises(ModelError) as e:
        load_onnx(models["vis"], DSINE_CONTRACT)
    msg = str(e.value)
    assert "vis.onnx" in msg and "missing input 'intrinsics'" in msg and "missing output 'normal'" in msg

    wrong = export(WrongNames(), (torch.zeros(1, 3, 8, 8),), tmp_path / "wrong.onnx", ["img"], ["feat"])
    with pytest.raises(ModelError) as e:
        load_onnx(wrong, VISMVSNET_FEATURES_CONTRACT)
    msg = str(e.value)
    assert "missing input 'image'" in msg and "unexpected input(s) ['img']" in msg and "missing output 'features'" in msg

    # Rank, dtype and fixed-dimension mismatches against hand-written contracts.
    rank3 = ModelContract("r", (TensorSpec("image", 3),), (TensorSpec("features", 4),))
    with pytest.raises(ModelError, match=r"input 'image' has rank 4 .*contract requires 3"):
        load_onnx(models["vis"], rank3)
    f16 = ModelContract("h", (TensorSpec("image", 4, "float16"),), (TensorSpec("features", 4),))
    with pytest.raises(ModelError, match=r"input 'image' has dtype float32, contract requires float16"):
        load_onnx(models["vis"], f16)
    ch64 = ModelContract("c", (TensorSpec("image", 4),), (TensorSpec("features", 4, "float32", (1, 64, None, None)),))
    with pytest.raises(ModelError, match=r"output 'features' dimension 1 is 32, contract requires 64"):
        load_onnx(models["vis"], ch64)


def test_run_validates_inputs_and_outputs(models, tmp_path):
    m = load_onnx(models["dsine"], DSINE_CONTRACT)
    K = np.eye(3, dtype=np.float32)[None]
    img = np.zeros((1, 3, 32, 32), np.float32)
    with pytest.raises(ModelError, match=r"takes inputs \['image', 'intrinsics'\]"):
        m.run(image=img)
    with pytest.raises(ModelError, match=r"input 'image' has dtype float64"):
        m.run(image=img.astype(np.float64), intrinsics=K)
    with pytest.raises(ModelError, match=r"input 'image' dimension 1 is 4, contract requires 3"):
        m.run(image=np.zeros((1, 4, 32, 32), np.float32), intrinsics=K)
    with pytest.raises(ModelError, match=r"input 'image' has rank 3"):
        m.run(image=img[0], intrinsics=K)
    bad = img.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(ModelError, match=r"input 'image' has non-finite values"):
        m.run(image=bad, intrinsics=K)

    nan_model = export_fake_vismvsnet(tmp_path / "nan.onnx", NaNFeatures())
    n = load_onnx(nan_model, VISMVSNET_FEATURES_CONTRACT)
    with pytest.raises(ModelError, match=r"nan\.onnx: .*output 'features' has non-finite values"):
        n.run(image=np.ones((1, 3, 8, 8), np.float32))
