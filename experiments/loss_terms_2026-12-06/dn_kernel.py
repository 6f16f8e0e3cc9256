"""L_dn's kernels (``pipeline.losses._dn_kernels``, landed from the prototype this file held
until 04d6c2b) against the torch composition ``normal._depth_normal_loss_torch``: value and
both gradients bit for bit on random maps (no-surface and flat patches included), and the
time of a forward and backward at training size.

    python experiments/loss_terms_2026-12-06/dn_kernel.py [H W]   (from the checkout)

The orders were found by ``dn_orders.py`` (a numpy emulation); they are listed in the kernels'
module docstring.
"""
from __future__ import annotations

import sys
import time

import numpy as np
import torch

from pipeline.losses.normal import _depth_normal_loss_torch, depth_normal_loss


def _case(fn, nr_base, depth0, alpha, K, weight):
    nrl, d = nr_base.clone().requires_grad_(True), depth0.clone().requires_grad_(True)
    loss = fn(nrl.permute(2, 0, 1), d, alpha, K)
    (weight * loss).backward()
    return loss.detach(), nrl.grad, d.grad


def main():
    H, W = (int(sys.argv[1]), int(sys.argv[2])) if len(sys.argv) > 2 else (300, 400)
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[0.75 * W, 0.0, W / 2 - 0.5], [0.0, 0.78 * W, H / 2 - 0.5], [0.0, 0.0, 1.0]])
    for trial in range(3):
        depth0 = (2.0 + 0.3 * torch.rand(H, W, generator=g)).float()
        depth0[3:6, 3:9] = 0.0  # no surface
        depth0[10:14, 10:12] = 2.0  # flat: equal depths
        nr_base = torch.randn(H, W, 3, generator=g)
        alpha = torch.rand(H, W, generator=g)
        w = torch.tensor(0.07 + trial)
        (la, gna, gda), (lb, gnb, gdb) = (_case(fn, nr_base, depth0, alpha, K, w)
                                          for fn in (_depth_normal_loss_torch, depth_normal_loss))
        print(f"trial {trial}: value {'identical' if torch.equal(la, lb) else 'differs'}, normal gradient "
              f"{'identical' if torch.equal(gna, gnb) else f'differs, max {(gna - gnb).abs().max().item():.3g}'}, depth gradient "
              f"{'identical' if torch.equal(gda, gdb) else f'differs, max {(gda - gdb).abs().max().item():.3g}'}")
    for name, fn in (("torch", _depth_normal_loss_torch), ("kernels", depth_normal_loss)):
        ts = []
        for _ in range(30):
            t = time.perf_counter()
            _case(fn, nr_base, depth0, alpha, K, w)
            ts.append(time.perf_counter() - t)
        print(f"{name}: forward + backward {np.median(ts[5:]) * 1e3:.2f} ms (median, {H}x{W})")


if __name__ == "__main__":
    main()
