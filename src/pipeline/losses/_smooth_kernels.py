"""L_smooth's per-pixel work as CPU kernels (numba, parallel over rows), float32.

The torch composition in :func:`pipeline.losses.smoothness._normal_smoothness_torch` is a
dozen passes over the map each way (normalise, four slices, differences, masks) and its
autograd; these two kernels do the forward and the backward in two passes each, in torch's
order of operations and of its engine's gradient accumulation, so that value and gradient
are torch's to the last bit (tested): trained models do not change with the path.

The orders that takes: torch's 2-norm over the channels is a plain sum of squares when the
channels are an outer axis (a contiguous ``(3, H, W)``) and fused multiply-adds when they are
the innermost one (the renders' ``(H, W, 3)`` seen as ``(3, H, W)``); the engine adds the
four slices' gradients as horizontal b, horizontal a, vertical b, vertical a (``+ 0`` where a
slice does not reach, as it adds zero-padded tensors); ``x / denom``'s backward is
``-g * ((x / denom) / denom)`` summed over the channels in order; the norm's is
``x / |x| * g``; ``sgn`` is 0 for NaN. Arrays are ``(H, W, 3)`` normals (any strides) and
C-contiguous maps.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

NORMALIZE_EPS = np.float32(1e-12)  # F.normalize's default


@intrinsic
def _fma32(typingctx, a, b, c):
    """float32 ``a * b + c`` rounded once (LLVM's fma): numba never contracts on its own."""
    def codegen(context, builder, signature, args):
        f = ir.FloatType()
        fma = builder.module.declare_intrinsic("llvm.fma", [f], ir.FunctionType(f, [f, f, f]))
        return builder.call(fma, args)
    return types.float32(types.float32, types.float32, types.float32), codegen


@njit(inline="always")
def _norm(x, i, j, fma):
    """torch's 2-norm over the channels of pixel (i, j): see the module's docstring."""
    if fma:
        a = _fma32(x[i, j, 2], x[i, j, 2], _fma32(x[i, j, 1], x[i, j, 1], x[i, j, 0] * x[i, j, 0]))
    else:
        a = x[i, j, 0] * x[i, j, 0]
        a = a + x[i, j, 1] * x[i, j, 1]
        a = a + x[i, j, 2] * x[i, j, 2]
    return np.sqrt(a)


@njit(parallel=True, cache=True, error_model="numpy")
def forward(x, e1, e2, ok1, ok2, fma, cl, nx, c1, c2):
    """From the normals ``x`` ``(H, W, 3)``: ``cl`` ``(H, W)`` their clamped norms, ``nx`` the
    normalised normals, ``c1`` ``(H-1, W)`` and ``c2`` ``(H, W-1)`` the masked costs of the
    vertical and horizontal pairs, ``where(ok, |a - b|_1 e, 0)`` with ``e`` the edge weights
    ``e1`` / ``e2`` and ``ok`` the pairs' masks ``ok1`` / ``ok2``."""
    H, W, _ = x.shape
    zero = np.float32(0.0)
    for i in prange(H):
        for j in range(W):
            nr = _norm(x, i, j, fma)
            cl[i, j] = NORMALIZE_EPS if nr < NORMALIZE_EPS else nr
            for c in range(3):
                nx[i, j, c] = x[i, j, c] / cl[i, j]
    for i in prange(H):
        for j in range(W):
            if i < H - 1:
                s = zero
                for c in range(3):
                    s = s + abs(nx[i, j, c] - nx[i + 1, j, c])
                c1[i, j] = s * e1[i, j] if ok1[i, j] else zero
            if j < W - 1:
                s = zero
                for c in range(3):
                    s = s + abs(nx[i, j, c] - nx[i, j + 1, c])
                c2[i, j] = s * e2[i, j] if ok2[i, j] else zero


@njit(inline="always")
def _sgn(v):
    """torch's sgn of a float32 (-1, 0, 1; 0 for NaN) without branches: neighbouring normals'
    differences have random signs, and branches on them mispredict."""
    return np.float32(v > 0) - np.float32(v < 0)


@njit(inline="always")
def _slices(gv, gh, i, j, c, H, W):
    """The normalised normal's gradient at (i, j, c): the four slices' gradients in the order
    torch's engine adds them."""
    zero = np.float32(0.0)
    t = -gh[i, j - 1, c] if j > 0 else zero
    t = t + (gh[i, j, c] if j < W - 1 else zero)
    t = t + (-gv[i - 1, j, c] if i > 0 else zero)
    return t + (gv[i, j, c] if i < H - 1 else zero)


@njit(parallel=True, cache=True, error_model="numpy")
def backward(x, e1, e2, ok1, ok2, fma, cl, nx, g1, gv, gh, gx):
    """``gx`` ``(H, W, 3)``: the gradient of the normals ``x`` for ``g1``, the loss's gradient
    over the pair count. First each pair's ``d|a - b|_1 / da`` (scratch ``gv`` ``(H-1, W, 3)``
    vertical, ``gh`` ``(H, W-1, 3)`` horizontal), then per pixel the slices' sum, the
    division's and the norm's backward."""
    H, W, _ = x.shape
    zero = np.float32(0.0)
    for i in prange(H):
        for j in range(W):
            if i < H - 1:
                gs = (g1 if ok1[i, j] else zero) * e1[i, j]
                for c in range(3):
                    gv[i, j, c] = gs * _sgn(nx[i, j, c] - nx[i + 1, j, c])
            if j < W - 1:
                gs = (g1 if ok2[i, j] else zero) * e2[i, j]
                for c in range(3):
                    gh[i, j, c] = gs * _sgn(nx[i, j, c] - nx[i, j + 1, c])
    for i in prange(H):
        for j in range(W):
            n0, n1, n2 = _slices(gv, gh, i, j, 0, H, W), _slices(gv, gh, i, j, 1, H, W), _slices(gv, gh, i, j, 2, H, W)
            c_ = cl[i, j]
            gcl = zero + (-n0) * (nx[i, j, 0] / c_)
            gcl = gcl + (-n1) * (nx[i, j, 1] / c_)
            gcl = gcl + (-n2) * (nx[i, j, 2] / c_)
            # Where |x| >= eps the clamped norm is |x| and x / |x| is nx; below, the clamp
            # passes no gradient (0 * x / |x|, NaN-free only where |x| > 0, as torch's).
            nr = c_ if c_ > NORMALIZE_EPS else _norm(x, i, j, fma)
            for c in range(3):
                if nr >= NORMALIZE_EPS:
                    gxn = nx[i, j, c] * gcl
                else:
                    gxn = zero if nr == 0 else (x[i, j, c] / nr) * zero
                gn = n0 if c == 0 else (n1 if c == 1 else n2)
                gx[i, j, c] = (zero + gn / c_) + gxn
