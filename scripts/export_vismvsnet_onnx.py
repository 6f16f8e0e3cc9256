#!/usr/bin/env python
"""Export Vis-MVSNet's feature extractor (finest level: 32 channels at 1/2 resolution) to
ONNX with the contract of ``pipeline.onnx_models.VISMVSNET_FEATURES_CONTRACT``.

Needs a checkout of the official code (github.com/jzhangbs/Vis-MVSNet) and its
pretrained checkpoint (a ``{step}.tar`` holding ``state_dict`` of the full model, saved
through ``nn.DataParallel``); neither ships with this repository, and this script is not
run by the tests. Example::

    python scripts/export_vismvsnet_onnx.py --repo ~/src/Vis-MVSNet \\
        --checkpoint ~/src/Vis-MVSNet/pretrained_model/vis/XXXX.tar --out models/vismvsnet_features.onnx

The model takes the preprocessed image (``pipeline.priors.features.vismvsnet_input``:
BGR, ImageNet mean/std) and returns ``FeatExt``'s third output.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch


class FinestFeatures(torch.nn.Module):
    """FeatExt returns (1/8, 1/4, 1/2)-resolution maps; GCGS uses the 1/2 one."""

    def __init__(self, feat_ext: torch.nn.Module) -> None:
        super().__init__()
        self.feat_ext = feat_ext

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.feat_ext(image)[2]


def import_featext(repo: Path):
    sys.path.insert(0, str(repo))
    # core/model_cas.py creates a CUDA tensor at import time; on a CPU-only machine make
    # .cuda() a no-op while importing it.
    if not torch.cuda.is_available():
        cuda = torch.Tensor.cuda
        torch.Tensor.cuda = lambda self, *a, **k: self
        try:
            from core.model_cas import FeatExt
        finally:
            torch.Tensor.cuda = cuda
    else:
        from core.model_cas import FeatExt
    return FeatExt


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repo", type=Path, required=True, help="Vis-MVSNet checkout")
    p.add_argument("--checkpoint", type=Path, required=True, help="checkpoint .tar with 'state_dict'")
    p.add_argument("--out", type=Path, default=Path("models/vismvsnet_features.onnx"))
    p.add_argument("--height", type=int, default=600, help="example input height (even)")
    p.add_argument("--width", type=int, default=800, help="example input width (even)")
    args = p.parse_args(argv)

    FeatExt = import_featext(args.repo)
    state = torch.load(args.checkpoint, map_location="cpu")["state_dict"]
    feat_state = {}
    for k, v in state.items():
        k = k.removeprefix("module.")
        if k.startswith("feat_ext."):
            feat_state[k.removeprefix("feat_ext.")] = v
    if not feat_state:
        raise SystemExit(f"{args.checkpoint}: no feat_ext.* weights in state_dict")
    feat = FeatExt()
    feat.load_state_dict(feat_state, strict=True)
    model = FinestFeatures(feat).eval()

    x = torch.zeros(1, 3, args.height, args.width)
    with torch.no_grad():
        y = model(x)
    if y.shape[1] != 32 or tuple(y.shape[2:]) != (args.height // 2, args.width // 2):
        raise SystemExit(f"unexpected feature shape {tuple(y.shape)} for input {tuple(x.shape)}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (x,), str(args.out), input_names=["image"], output_names=["features"],
                          dynamic_axes={"image": {2: "H", 3: "W"}, "features": {2: "h", 3: "w"}},
                          opset_version=17, dynamo=False)

    # Check the file against the contract the pipeline will apply.
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from pipeline.onnx_models import VISMVSNET_FEATURES_CONTRACT, load_onnx

    m = load_onnx(args.out, VISMVSNET_FEATURES_CONTRACT, providers=["CPUExecutionProvider"])
    out = m.run(image=x.numpy())["features"]
    err = float(abs(out - y.numpy()).max())
    print(f"wrote {args.out}: features {out.shape}, max |onnx - torch| = {err:.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
