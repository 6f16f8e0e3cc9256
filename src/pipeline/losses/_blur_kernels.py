"""SSIM's separable Gaussian blur as a CPU kernel (numba, parallel over image rows).

torch's depthwise ``conv2d`` took ~4 ms a pass for the 15 channels of SSIM's moments at
400x300 (mkldnn has no fast path for 1-D depthwise kernels), a sixth of a training iteration;
these loops run both passes in ~1.7 ms. The torch composition in
:func:`pipeline.losses.photometric._blur_torch` is the reference they are tested against.
"""
from __future__ import annotations

import numpy as np
from numba import njit, prange

_CHUNKS = 64  # row chunks per pass: enough to balance the threads


@njit(parallel=True, cache=True, error_model="numpy")
def gaussian_blur(src, g, tmp, out):
    """``out[c]``: ``src[c]`` convolved with the symmetric 1-D kernel ``g`` along rows, then
    along columns, zero padding (as ``conv2d`` with ``padding=len(g) // 2``). ``src``, ``tmp``
    and ``out`` are C-contiguous ``(N, H, W)`` arrays of one dtype; ``tmp`` is scratch."""
    n, h, w = src.shape
    win = g.shape[0]
    pad = win // 2
    rows = n * h
    # Rows in chunks, each with its own scratch rows: one allocation per chunk, not per row.
    chunks = min(rows, _CHUNKS)
    for ch in prange(chunks):
        padded = np.zeros(w + 2 * pad, src.dtype)
        acc = np.empty(w, src.dtype)
        for r in range(rows * ch // chunks, rows * (ch + 1) // chunks):
            c = r // h
            y = r - c * h
            padded[pad:pad + w] = src[c, y]
            acc[:] = 0
            for k in range(win):  # shifted rows: contiguous loops the compiler vectorises
                gk = g[k]
                for x in range(w):
                    acc[x] += gk * padded[x + k]
            tmp[c, y] = acc
    for ch in prange(chunks):
        for r in range(rows * ch // chunks, rows * (ch + 1) // chunks):
            c = r // h
            y = r - c * h
            acc = out[c, y]
            acc[:] = 0
            for k in range(win):
                yy = y + k - pad
                if yy >= 0 and yy < h:
                    gk = g[k]
                    t = tmp[c, yy]
                    for x in range(w):
                        acc[x] += gk * t[x]
