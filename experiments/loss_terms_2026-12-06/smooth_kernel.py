"""A prototype: L_smooth (``losses.smoothness.normal_smoothness_loss``) with its per-pixel work in
numba kernels that repeat torch's operations in torch's order, forward and backward (the sums
over the map left to torch), checked bit for bit against the torch composition, and timed.

What bit for bit took: torch's 2-norm over the channels is a plain sum of squares over an
outer axis but fused multiply-adds over the innermost one (the renders' ``(H, W, 3)`` permuted);
the engine adds the four slices' gradients as horizontal b, horizontal a, vertical b, vertical a
(zero-padded tensors, so ``+ 0`` where a slice does not reach); ``x / denom``'s backward is
``-g * ((x / denom) / denom)`` summed over the channels in order; the norm's is
``x / |x| * g``; ``sgn`` is 0 for NaN. A training of synth_relief with it in place of the torch
term (``optimize.train.normal_smoothness_loss`` patched) ends with every parameter bit for bit
the torch term's (docs/notes/2026-12-06-at-the-line.md).

    python experiments/loss_terms_2026-12-06/smooth_kernel.py [H W]   (from the checkout)

The kernels compile on each run (``cache=False``: a module loaded by path cannot use numba's cache).
"""
from __future__ import annotations

import sys
import time

import numpy as np
import torch
from llvmlite import ir
from numba import njit, prange, types
from numba.extending import intrinsic

from pipeline.losses.smoothness import normal_smoothness_loss

EPS = np.float32(1e-12)  # F.normalize's


@intrinsic
def _fma32(typingctx, a, b, c):
    """float32 ``a * b + c`` rounded once (LLVM's fma)."""
    def codegen(context, builder, signature, args):
        f = ir.FloatType()
        return builder.call(builder.module.declare_intrinsic("llvm.fma", [f], ir.FunctionType(f, [f, f, f])), args)
    return types.float32(types.float32, types.float32, types.float32), codegen


@njit(inline="always")
def _norm(x, i, j, fma):
    """torch's 2-norm over the channels: over an outer axis (a contiguous ``(3, H, W)``) a
    plain sum of squares, over the innermost one (the renders' ``(H, W, 3)`` permuted) fused
    multiply-adds."""
    if fma:
        a = _fma32(x[i, j, 2], x[i, j, 2], _fma32(x[i, j, 1], x[i, j, 1], x[i, j, 0] * x[i, j, 0]))
    else:
        a = x[i, j, 0] * x[i, j, 0]
        a = a + x[i, j, 1] * x[i, j, 1]
        a = a + x[i, j, 2] * x[i, j, 2]
    return np.sqrt(a)


@njit(parallel=True, cache=False, error_model="numpy")
def _forward(x, e1, e2, ok1, ok2, fma, cl, nx, c1, c2):
    """``cl``: the clamped norms, ``nx`` the normalised normals; ``c1`` / ``c2``: the masked costs of the vertical and the
    horizontal pairs (torch's ``where(ok, |a - b|.sum(0) * exp(...), 0)``)."""
    H, W, _ = x.shape
    zero = np.float32(0.0)
    for i in prange(H):
        for j in range(W):
            nr = _norm(x, i, j, fma)
            cl[i, j] = EPS if nr < EPS else nr
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
    """torch's sgn of a float32 (-1, 0, 1; 0 for NaN), without branches: the signs of
    neighbouring normals' differences are random, and branches on them mispredict."""
    return np.float32(v > 0) - np.float32(v < 0)


@njit(inline="always")
def _slices(gv, gh, i, j, c, H, W):
    """The normalised normal's gradient at (i, j, c): the four slices' gradients in the order
    torch's engine adds them (horizontal b, horizontal a, vertical b, vertical a; + 0 for a
    slice that does not reach the pixel, as the engine adds its zero-padded tensor)."""
    zero = np.float32(0.0)
    t = -gh[i, j - 1, c] if j > 0 else zero
    t = t + (gh[i, j, c] if j < W - 1 else zero)
    t = t + (-gv[i - 1, j, c] if i > 0 else zero)
    return t + (gv[i, j, c] if i < H - 1 else zero)


@njit(parallel=True, cache=False, error_model="numpy")
def _backward(x, e1, e2, ok1, ok2, fma, cl, nx, g1, gv, gh, gx):
    """``gx``: the gradient of the normals ``x`` for an incoming ``g1`` (the loss's gradient
    over the pair count): first each pair's ``d|a - b| / da`` (``gv`` vertical, ``gh``
    horizontal), then per pixel the slices' sum (:func:`_slices`), ``/ denom`` and the norm's."""
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
            # F.normalize's x / denom: d/dx = g / denom, d/ddenom = -g * ((x / denom) / denom),
            # summed over the channels in order
            gcl = zero + (-n0) * (nx[i, j, 0] / c_)
            gcl = gcl + (-n1) * (nx[i, j, 1] / c_)
            gcl = gcl + (-n2) * (nx[i, j, 2] / c_)
            # linalg_vector_norm's backward, x / |x| * grad (0 where |x| = 0): where |x| >= EPS,
            # cl = |x| and x / |x| is nx; below, the clamp passes no gradient.
            nr = c_ if c_ > EPS else _norm(x, i, j, fma)
            for c in range(3):
                if nr >= EPS:
                    gxn = nx[i, j, c] * gcl
                else:
                    gxn = zero if nr == 0 else (x[i, j, c] / nr) * zero
                gn = n0 if c == 0 else (n1 if c == 1 else n2)
                gx[i, j, c] = (zero + gn / c_) + gxn


class _Smooth(torch.autograd.Function):
    @staticmethod
    def forward(ctx, normal, e1, e2, ok1, ok2, count):
        # torch's norm takes another order of operations over the innermost axis
        fma = normal.stride(0) == 1
        x = normal.detach().permute(1, 2, 0).numpy()  # (H, W, 3): the renders' own layout
        H, W = x.shape[:2]
        cl, nx = np.empty((H, W), np.float32), np.empty((H, W, 3), np.float32)
        c1, c2 = np.zeros((H - 1, W), np.float32), np.zeros((H, W - 1), np.float32)
        args = [t.contiguous().numpy() for t in (e1, e2, ok1, ok2)]
        _forward(x, *args, fma, cl, nx, c1, c2)
        total = normal.detach().sum() * 0.0
        total = total + torch.from_numpy(c1).sum()
        total = total + torch.from_numpy(c2).sum()
        ctx.save = (x, args, fma, cl, nx, count)
        return total / max(count, 1)

    @staticmethod
    def backward(ctx, g):
        x, args, fma, cl, nx, count = ctx.save
        g1 = (g / max(count, 1)).item()
        gx = np.empty_like(x)
        H, W, _ = x.shape
        gv, gh = np.empty((H - 1, W, 3), np.float32), np.empty((H, W - 1, 3), np.float32)
        _backward(x, *args, fma, cl, nx, np.float32(g1), gv, gh, gx)
        return torch.from_numpy(gx).permute(2, 0, 1), None, None, None, None, None


def smooth_fused(normal, image, valid, gamma):
    image = image.detach()
    es, oks = [], []
    for dim in (1, 2):
        size = normal.shape[dim] - 1
        oks.append(valid.narrow(dim - 1, 0, size) & valid.narrow(dim - 1, 1, size))
        edge = (image.narrow(dim, 0, size) - image.narrow(dim, 1, size)).abs().mean(0)
        es.append(torch.exp(-gamma * edge))
    count = int(oks[0].sum()) + int(oks[1].sum())
    return _Smooth.apply(normal, es[0], es[1], oks[0], oks[1], count)


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
            (la, ga), (lb, gb) = (_case(fn, base, image, valid, w, permuted) for fn in (normal_smoothness_loss, smooth_fused))
            print(f"trial {trial}, {'(H, W, 3) permuted' if permuted else '(3, H, W) contiguous'}: value "
                  f"{'identical' if torch.equal(la, lb) else 'differs'}, gradient "
                  f"{'identical' if torch.equal(ga, gb) else f'differs, max {(ga - gb).abs().max().item():.3g}'}")
    for name, fn in (("torch", normal_smoothness_loss), ("kernels", smooth_fused)):
        ts = []
        for _ in range(30):
            t = time.perf_counter()
            _case(fn, base, image, valid, w, True)
            ts.append(time.perf_counter() - t)
        print(f"{name}: forward + backward {np.median(ts[5:]) * 1e3:.2f} ms (median, {H}x{W}, the renders' layout)")


if __name__ == "__main__":
    main()
