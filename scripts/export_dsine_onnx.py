#!/usr/bin/env python
"""Export DSINE (v02) to ONNX with the contract of ``pipeline.onnx_models.DSINE_CONTRACT``.

Needs a checkout of the official code (github.com/baegwangbin/DSINE) with its
dependencies (``geffnet``) and the checkpoint ``dsine.pt``; neither ships with this
repository, and this script is not run by the tests. Example::

    python scripts/export_dsine_onnx.py --repo ~/src/DSINE \\
        --config projects/dsine/experiments/exp001_cvpr2024/dsine.txt \\
        --checkpoint ~/src/DSINE/projects/dsine/checkpoints/exp001_cvpr2024/dsine.pt \\
        --height 608 --width 800 --out models/dsine.onnx

Export at the scene's size padded to multiples of 32 (800x600 -> 800x608): DSINE's
forward computes its ray grids from Python integers of the input shape, which the
exporter freezes, so the exported graph is valid for that size only (onnxruntime then
rejects other sizes, and ``gcgs priors`` reports it naming the model file).

Inputs: ``image`` (1, 3, H, W) ImageNet-normalised RGB, zero-padded (before
normalisation) to multiples of 32; ``intrinsics`` (1, 3, 3) of the padded image, integer
pixel centres. Output: ``normal`` (1, 3, H, W), DSINE's convention: OpenCV axes, pointing
away from the camera (``pipeline.priors.normals`` negates it).
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from pathlib import Path

import torch


class Wrapped(torch.nn.Module):
    """DSINE's forward returns the list of refinement outputs; keep the last one."""

    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        # DSINE shifts the principal point in place; work on a copy of the input.
        return self.model(image, intrins=intrinsics.clone(), mode="test")[-1]


def build_model(repo: Path, config: str, checkpoint: Path) -> torch.nn.Module:
    sys.path.insert(0, str(repo))
    os.chdir(repo / "projects" / "dsine")  # DSINE's config parser resolves paths from here
    sys.argv = [sys.argv[0], config]
    import projects.dsine.config as dsine_config

    args = dsine_config.get_args(test=True)
    from models.dsine.v02 import DSINE_v02

    # DSINE_v02 puts its pixel grid on CUDA device 0 in __init__; keep it on the CPU
    # when there is no GPU.
    to = torch.Tensor.to
    if not torch.cuda.is_available():
        torch.Tensor.to = lambda self, *a, **k: self if a and a[0] == 0 else to(self, *a, **k)
    try:
        model = DSINE_v02(args)
    finally:
        torch.Tensor.to = to
    state = torch.load(checkpoint, map_location="cpu")["model"]
    model.load_state_dict({k.removeprefix("module."): v for k, v in state.items()}, strict=True)
    return Wrapped(model.eval())


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repo", type=Path, required=True, help="DSINE checkout")
    p.add_argument("--config", required=True, help="experiment config, relative to projects/dsine/")
    p.add_argument("--checkpoint", type=Path, required=True, help="dsine.pt")
    p.add_argument("--height", type=int, default=608, help="input height, multiple of 32")
    p.add_argument("--width", type=int, default=800, help="input width, multiple of 32")
    p.add_argument("--out", type=Path, default=Path("models/dsine.onnx"))
    args = p.parse_args(argv)
    if args.height % 32 or args.width % 32:
        raise SystemExit("--height and --width must be multiples of 32")
    out = args.out.resolve()
    repo_src = Path(__file__).resolve().parents[1] / "src"
    model = build_model(args.repo.resolve(), args.config, args.checkpoint.resolve())

    x = torch.zeros(1, 3, args.height, args.width)
    K = torch.tensor([[[1000.0, 0.0, args.width / 2 - 0.5], [0.0, 1000.0, args.height / 2 - 0.5], [0.0, 0.0, 1.0]]])
    with torch.no_grad():
        y = model(x, K)
    out.parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, (x, K), str(out), input_names=["image", "intrinsics"], output_names=["normal"],
                          opset_version=17, dynamo=False)

    sys.path.insert(0, str(repo_src))
    from pipeline.onnx_models import DSINE_CONTRACT, load_onnx

    m = load_onnx(out, DSINE_CONTRACT, providers=["CPUExecutionProvider"])
    n = m.run(image=x.numpy(), intrinsics=K.numpy())["normal"]
    print(f"wrote {out}: normal {n.shape}, max |onnx - torch| = {float(abs(n - y.numpy()).max()):.2e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
