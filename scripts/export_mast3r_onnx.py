#!/usr/bin/env python
"""Export MASt3R's pair head to ONNX in the form the ``mast3r`` init backend expects.

Run this on a machine that has the official MASt3R code (github.com/naver/mast3r, with
its dust3r submodule, importable as ``mast3r`` and ``dust3r``) and a checkpoint, e.g.
``MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth``. It is not run by the tests
(no weights can be downloaded here); tests/mast3r_helpers.py exports a tiny model with
the same contract.

Contract (docs/init.md, ``pipeline.init.mast3r.MAST3R_CONTRACT``):
  inputs  img1, img2: float32 (1, 3, H, W), RGB scaled to [-1, 1] (dust3r's ImgNorm)
  outputs pts3d_1: float32 (1, H, W, 3)  view-1 points in camera 1's frame
          conf_1:  float32 (1, H, W)     their confidence (>= 1)
          pts3d_2: float32 (1, H, W, 3)  view-2 points in camera 1's frame
          conf_2:  float32 (1, H, W)
H and W are fixed at export (default 384 x 512, the landscape 4:3 size MASt3R uses at
512 px for 800x600 images); the backend reads them from the file. Export on CPU so that
RoPE uses its PyTorch implementation (the CUDA "curope" kernel has no ONNX export).

    python scripts/export_mast3r_onnx.py --weights CKPT.pth --out models/mast3r_512.onnx
"""
from __future__ import annotations

import argparse
import sys

import torch


class MASt3RPair(torch.nn.Module):
    """Wraps ``AsymmetricMASt3R.forward(view1, view2)`` to take and give plain tensors."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, img1: torch.Tensor, img2: torch.Tensor):
        h, w = img1.shape[-2:]
        shape = torch.tensor([[h, w]], dtype=torch.int32)
        # 'instance' differs between the views: dust3r's is_symmetrized() is then False for
        # a batch of one, and both images are encoded in one pass.
        view1 = {"img": img1, "true_shape": shape, "instance": ["0"]}
        view2 = {"img": img2, "true_shape": shape, "instance": ["1"]}
        res1, res2 = self.model(view1, view2)
        return res1["pts3d"], res1["conf"], res2["pts3d_in_other_view"], res2["conf"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--weights", required=True, help="MASt3R checkpoint (.pth) or Hugging Face name")
    p.add_argument("--out", required=True, help="ONNX file to write")
    p.add_argument("--height", type=int, default=384)
    p.add_argument("--width", type=int, default=512)
    p.add_argument("--opset", type=int, default=17)
    args = p.parse_args(argv)
    if args.height % 16 or args.width % 16:
        p.error("height and width must be multiples of 16 (the ViT patch size)")
    try:
        from mast3r.model import AsymmetricMASt3R
    except ImportError as exc:
        print(f"export_mast3r_onnx: the official MASt3R code is not importable ({exc}); "
              "clone github.com/naver/mast3r with its submodules and add it to PYTHONPATH", file=sys.stderr)
        return 1
    model = AsymmetricMASt3R.from_pretrained(args.weights).to("cpu").eval()
    wrapped = MASt3RPair(model).eval()
    x = torch.zeros(1, 3, args.height, args.width)
    with torch.no_grad():
        pts1, conf1, pts2, conf2 = wrapped(x, x)
    expected = (1, args.height, args.width)
    if tuple(pts1.shape) != expected + (3,) or tuple(conf1.shape) != expected or tuple(pts2.shape) != expected + (3,):
        print(f"export_mast3r_onnx: unexpected output shapes {tuple(pts1.shape)}, {tuple(conf1.shape)}, "
              f"{tuple(pts2.shape)}, {tuple(conf2.shape)}", file=sys.stderr)
        return 1
    torch.onnx.export(wrapped, (x, x), args.out, input_names=["img1", "img2"],
                      output_names=["pts3d_1", "conf_1", "pts3d_2", "conf_2"], opset_version=args.opset,
                      dynamo=False, do_constant_folding=True)
    # Check the file against the backend's contract when this package is importable too.
    try:
        from pipeline.init.mast3r import MAST3R_CONTRACT
        from pipeline.onnx_models import load_onnx
    except ImportError:
        print(f"wrote {args.out} (contract not checked: the gcgs package is not installed here)")
        return 0
    load_onnx(args.out, MAST3R_CONTRACT, providers=["CPUExecutionProvider"])
    print(f"wrote {args.out}; it follows the mast3r contract")
    return 0


if __name__ == "__main__":
    sys.exit(main())
