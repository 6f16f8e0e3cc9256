"""SSIM's per-pixel arithmetic as CPU kernels (numba, parallel over chunks of pixels).

The closed-form SSIM of :class:`pipeline.losses.photometric._SSIMOfFirst` is a dozen torch
element-wise operations on each side of its blurs, each a pass over the image and a new
tensor. These kernels do each side in one pass, operation by operation in the same order and
precision as the torch expressions in ``photometric.py``, which are their reference (tested
equal bit for bit). Arrays are C-contiguous and flat; the constants come in the arrays' dtype.
"""
from __future__ import annotations

from numba import njit, prange

_CHUNKS = 64  # pixel chunks per pass: enough to balance the threads


@njit(parallel=True, cache=True, error_model="numpy")
def moments_input(img1, img2, out):
    """``out``: ``[img1, img2, img1^2, img2^2, img1 img2]`` end to end (the blur's input)."""
    n = img1.shape[0]
    chunks = max(1, min(n, _CHUNKS))
    for ch in prange(chunks):
        for i in range(n * ch // chunks, n * (ch + 1) // chunks):
            x, y = img1[i], img2[i]
            out[i] = x
            out[n + i] = y
            out[2 * n + i] = x * x
            out[3 * n + i] = y * y
            out[4 * n + i] = x * y


@njit(parallel=True, cache=True, error_model="numpy")
def parts(blurred, two, c1, c2, a1, a2, b1, b2, ssim_map):
    """From the blurred moments ``[mu1, mu2, E11, E22, E12]`` (end to end): the SSIM map's
    factors ``a1 a2 / (b1 b2)`` and the map."""
    n = a1.shape[0]
    chunks = max(1, min(n, _CHUNKS))
    for ch in prange(chunks):
        for i in range(n * ch // chunks, n * (ch + 1) // chunks):
            mu1, mu2 = blurred[i], blurred[n + i]
            e11, e22, e12 = blurred[2 * n + i], blurred[3 * n + i], blurred[4 * n + i]
            p1 = two * mu1 * mu2 + c1
            p2 = two * (e12 - mu1 * mu2) + c2
            q1 = mu1 * mu1 + mu2 * mu2 + c1
            q2 = (e11 - mu1 * mu1) + (e22 - mu2 * mu2) + c2
            a1[i], a2[i], b1[i], b2[i] = p1, p2, q1, q2
            ssim_map[i] = p1 * p2 / (q1 * q2)


@njit(parallel=True, cache=True, error_model="numpy")
def sensitivities(mu1, mu2, a1, a2, b1, b2, ssim_map, scale, two, out):
    """``out``: the mean SSIM's sensitivities to ``mu1``, ``E11`` and ``E12`` end to end (the
    blur's input in the backward), ``scale`` the incoming gradient over the pixel count."""
    n = a1.shape[0]
    chunks = max(1, min(n, _CHUNKS))
    for ch in prange(chunks):
        for i in range(n * ch // chunks, n * (ch + 1) // chunks):
            s = ssim_map[i]
            inv = scale / (b1[i] * b2[i])
            out[i] = two * mu2[i] * (a2[i] - a1[i]) * inv - two * mu1[i] * s * (b2[i] - b1[i]) * inv
            out[n + i] = -s * scale / b2[i]
            out[2 * n + i] = two * a1[i] * inv


@njit(parallel=True, cache=True, error_model="numpy")
def chain(blurred, img1, img2, two, out):
    """``out``: the gradient of the first image from the blurred sensitivities
    ``[g_mu1, g_E11, g_E12]`` (end to end)."""
    n = img1.shape[0]
    chunks = max(1, min(n, _CHUNKS))
    for ch in prange(chunks):
        for i in range(n * ch // chunks, n * (ch + 1) // chunks):
            out[i] = blurred[i] + two * img1[i] * blurred[n + i] + img2[i] * blurred[2 * n + i]
