"""``gcgs masks --model``: a salient-object ONNX model deciding inside the band around the 3D
labelling's projection (pipeline.masks.SaliencyModel), on tiny models the tests export
(no weights are bundled or downloaded)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
import torch

from onnx_helpers import export, export_fake_dsine
from pipeline import masks as M
from pipeline.onnx_models import ModelError
from test_masks import VIEWS, labels_of


class RedChannel(torch.nn.Module):
    """Saliency = the image's red channel undone from ImageNet normalisation, as logits
    (values outside [0, 1] after the affine map) or as a map in [0, 1]."""

    def __init__(self, logits: bool) -> None:
        super().__init__()
        self.logits = logits

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        red = image[:, 0:1] * 0.229 + 0.485
        return 8.0 * (red - 0.5) if self.logits else red


class Constant(torch.nn.Module):
    """A constant map (min-max normalised to 0: nothing salient), or with ``top_row_zero``
    1 everywhere but the top row (everything else salient)."""

    def __init__(self, top_row_zero: bool) -> None:
        super().__init__()
        self.top_row_zero = top_row_zero

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        ones = image[:, 0:1] * 0.0 + 1.0
        return torch.nn.functional.pad(ones[:, :, 1:], (0, 0, 1, 0), value=0.0) if self.top_row_zero else ones


def model_file(tmp_path, module, name: str, size: tuple[int, int] | None = (64, 64)):
    dyn = None if size is not None else {"input": {2: "H", 3: "W"}, "output": {2: "H", 3: "W"}}
    return export(module, (torch.zeros(1, 3, *(size or (48, 48))),), tmp_path / f"{name}.onnx", ["input"], ["output"], dyn)


@pytest.mark.parametrize("logits", [False, True])
def test_the_map_is_the_models_output_normalised_and_resized(tmp_path, logits):
    """The image goes in scaled to a maximum of 1 and ImageNet-normalised, at the model's
    fixed size; the map comes back min-max normalised at the image's size (a sigmoid first
    for logits)."""
    H, W = 48, 80
    yy, xx = np.mgrid[0:H, 0:W]
    image = np.zeros((H, W, 3))
    image[..., 0] = 0.4 * xx / (W - 1)  # a ramp, max 0.4: scaled to 1 before the model
    image[..., 1] = 0.1
    model = M.SaliencyModel(model_file(tmp_path, RedChannel(logits), "red"))
    assert model.size == (64, 64)
    sal = model(image)
    assert sal.shape == (H, W) and sal.min() >= 0.0 and sal.max() <= 1.0
    red = xx / (W - 1)  # after the scaling to a maximum of 1
    expected = 1.0 / (1.0 + np.exp(-8.0 * (red - 0.5))) if logits else red
    expected = (expected - expected.min()) / (expected.max() - expected.min())
    assert np.abs(sal - expected)[:, 3:-3].max() < 0.06  # two resizes (64 px in, 80 px back)
    assert np.corrcoef(sal.ravel(), expected.ravel())[0, 1] > 0.99


def test_a_model_without_a_fixed_size_runs_at_the_given_size(tmp_path):
    model = M.SaliencyModel(model_file(tmp_path, RedChannel(False), "free", size=None), size=96)
    assert model.size == (96, 96)
    assert model(np.random.default_rng(0).random((30, 50, 3))).shape == (30, 50)


def test_models_of_another_layout_are_refused_naming_the_file(tmp_path):
    bad = export_fake_dsine(tmp_path / "dsine.onnx")  # two inputs: image and intrinsics
    with pytest.raises(ModelError, match=r"dsine\.onnx: not a salient-object model"):
        M.SaliencyModel(bad)
    with pytest.raises(ModelError, match="not found"):
        M.SaliencyModel(tmp_path / "missing.onnx")
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ModelError, match="junk.onnx: not a loadable ONNX model"):
        M.SaliencyModel(junk)


def test_the_model_decides_only_inside_the_band(scenes, tmp_path):
    """A model that calls everything salient gets the projection grown by the band, no
    more; one that calls nothing salient keeps the projection's inner part: outside the
    band the 3D labelling decides, whatever the model says."""
    views = scenes["synth_relief"]
    labels = labels_of(views, views.depths)
    ones = M.SaliencyModel(model_file(tmp_path, Constant(True), "ones"))
    zeros = M.SaliencyModel(model_file(tmp_path, Constant(False), "zeros"))
    band = round(0.05 * max(views.images.shape[1:3]))
    for model, check in ((ones, "all"), (zeros, "none")):
        out = M.derive_masks(views.images, views.K, views.world_to_cam, views.depths, labels, VIEWS, saliency=model)
        for r in out:
            proj = r.stages["projection"]
            outer = scipy.ndimage.binary_dilation(proj, iterations=band)
            inner = scipy.ndimage.binary_erosion(proj, iterations=band, border_value=1)
            assert not (r.stages["refined"] & ~outer).any()
            if check == "all":
                assert r.method == "model", r.warnings
                assert r.stages["refined"].sum() >= 0.98 * outer.sum()
            else:  # a constant map normalises to 0: nothing salient, the sure foreground stays
                # (and the self-check then finds the band's object points missing: the fallback)
                assert r.method == "fallback_region" and "two views agree on" in r.warnings[0]
                assert not (r.stages["refined"] & ~inner).any() and r.stages["refined"].sum() > 0.5 * inner.sum()


@pytest.fixture(scope="module")
def scenes(cams):
    from pipeline.synth import build_scene
    from test_masks import render
    return {"synth_relief": render(build_scene("synth_relief", 0, cams), cams)}


@pytest.fixture(scope="module")
def cams(bundled_scan):
    from pipeline.data import dtu
    return dtu.load_cameras(bundled_scan)
