"""L_smooth's kernels (``pipeline.losses._smooth_kernels``, landed from the prototype this file
held until 04d6c2b) against the torch composition ``smoothness._normal_smoothness_torch``:
value and gradient bit for bit on random maps in both layouts, and the time of a forward and
backward at training size.

    python experiments/loss_terms_2026-12-06/smooth_kernel.py [H W]   (from the checkout)

The orders that bit for bit took are in the kernels' module docstring and
docs/notes/2026-12-06-at-the-line.md.
"""
from __future__ import annotations

import sys
import time

import numpy as np
import torch

from pipeline.losses.smoothness import _normal_smoothness_torch, normal_smoothness_loss


def _case(fn, base, image, valid, weight, permuted):
    leaf = base.clone().requires_grad_(True)
    normal = leaf.permute(2, 0, 1) if permuted else leaf.permute(2, 0, 1).contiguous()
    loss = fn(normal, image, valid, 10.0)
    (weight * loss).backward()
    return loss.detach(), leaf.grad


def main():
    H, W = (int(sys.argv[1]), int(sys.argv[2])) if len(sys.argv) > 2 else (300, 400)
    g = torch.Generator().manual_seed(0)
    for trial in range(3):
        base = torch.randn(H, W, 3, generator=g)
        base[:5, :5] = 0.0  # zero normals
        image = torch.rand(3, H, W, generator=g)
        valid = torch.rand(H, W, generator=g) > 0.3
        w = torch.tensor(0.05 + trial)
        for permuted in (True, False):
            (la, ga), (lb, gb) = (_case(fn, base, image, valid, w, permuted)
                                  for fn in (_normal_smoothness_torch, normal_smoothness_loss))
            print(f"trial {trial}, {'(H, W, 3) permuted' if permuted else '(3, H, W) contiguous'}: value "
                  f"{'identical' if torch.equal(la, lb) else 'differs'}, gradient "
                  f"{'identical' if torch.equal(ga, gb) else f'differs, max {(ga - gb).abs().max().item():.3g}'}")
    for name, fn in (("torch", _normal_smoothness_torch), ("kernels", normal_smoothness_loss)):
        ts = []
        for _ in range(30):
            t = time.perf_counter()
            _case(fn, base, image, valid, w, True)
            ts.append(time.perf_counter() - t)
        print(f"{name}: forward + backward {np.median(ts[5:]) * 1e3:.2f} ms (median, {H}x{W}, the renders' layout)")


if __name__ == "__main__":
    main()
