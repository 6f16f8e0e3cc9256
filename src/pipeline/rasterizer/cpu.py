"""The ``cpu`` backend: a torch.autograd.Function around the numba kernels.

Why numba rather than a torch C++/OpenMP extension: both were measured 3-8x faster
than pure torch here, but numba needs no compiler toolchain at install or run time,
caches its machine code next to the module (``cache=True``; the first use in a fresh
checkout compiles for ~tens of seconds, later processes load in well under a second),
and specialises the same source for float32 and float64 (float64 is what gradcheck
needs).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from pipeline.rasterizer import _kernels as K
from pipeline.rasterizer.project import Projected
from pipeline.rasterizer.types import Camera

_compile_seconds: float | None = None


@dataclass
class Bins:
    """Tile binning of one (surfels, camera) pair; see ``_kernels.bin_tiles``."""

    tile_start: np.ndarray
    tile_list: np.ndarray
    emit_start: np.ndarray
    slot_of_emit: np.ndarray
    tile_order: np.ndarray  # tiles by decreasing pair count, for load balance
    box: np.ndarray
    n_tx: int

    @property
    def num_pairs(self) -> int:
        return int(self.tile_list.shape[0])


def warm_up() -> float:
    """Compile (or load from numba's cache) every kernel for float32 and float64 on a
    tiny scene; returns the seconds it took in this process (0 after the first call)."""
    global _compile_seconds
    if _compile_seconds is not None:
        return 0.0
    from pipeline.rasterizer import Surfels, rasterize

    t0 = time.perf_counter()
    cam = Camera(K=np.array([[8.0, 0, 4], [0, 8.0, 4], [0, 0, 1]]), world_to_cam=np.eye(4), width=8, height=8)
    for dtype in (torch.float32, torch.float64):
        s = Surfels(
            means=torch.tensor([[0.0, 0.0, 2.0]], dtype=dtype),
            quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype),
            scales=torch.full((1, 2), 0.2, dtype=dtype, requires_grad=True),
            opacities=torch.tensor([0.5], dtype=dtype),
            features=torch.ones(1, 3, dtype=dtype),
        )
        out = rasterize(s, cam, backend="cpu")
        (out.features.sum() + out.distortion.sum() + out.depth_median.sum()).backward()
    _compile_seconds = time.perf_counter() - t0
    return _compile_seconds


def make_bins(proj: Projected, camera: Camera) -> Bins:
    n_tx = -(-camera.width // K.TILE)
    n_ty = -(-camera.height // K.TILE)
    box = np.ascontiguousarray(proj.box.numpy())
    order = np.ascontiguousarray(proj.order.numpy())
    tile_start, tile_list, emit_start, slot_of_emit = K.bin_tiles(order, box, n_tx, n_ty)
    tile_order = np.argsort(-np.diff(tile_start), kind="stable")
    return Bins(tile_start, tile_list, emit_start, slot_of_emit, tile_order, box, n_tx)


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, T: Tensor, opacities: Tensor, normals: Tensor, colors: Tensor, bins: Bins, camera: Camera):
        H, W = camera.height, camera.width
        P, C = colors.shape
        dtype = np.float64 if T.dtype == torch.float64 else np.float32
        Tm = _np(T.reshape(P, 9))
        opac, nrm, feat = _np(opacities), _np(normals), _np(colors)
        out_feat = np.empty((H, W, C), dtype)
        out_nrm = np.empty((H, W, 3), dtype)
        out_alpha, out_dsum, out_med, out_dist = (np.empty((H, W), dtype) for _ in range(4))
        aux = [np.empty((H, W), np.float64) for _ in range(4)]
        n_contrib = np.empty((H, W), np.int32)
        med_local = np.empty((H, W), np.int32)
        with numba.parallel_chunksize(1):
            K.forward(
                bins.tile_start, bins.tile_list, bins.tile_order, bins.box, Tm, opac, nrm, feat, W, bins.n_tx,
                camera.near, camera.far, out_feat, out_alpha, out_dsum, out_nrm, out_med, out_dist,
                *aux, n_contrib, med_local,
            )  # fmt: skip
        ctx.state = (Tm, opac, nrm, feat, bins, camera, aux, n_contrib, med_local)
        return tuple(torch.from_numpy(a) for a in (out_feat, out_alpha, out_dsum, out_nrm, out_med, out_dist))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_feat, g_alpha, g_dsum, g_nrm, g_med, g_dist):
        Tm, opac, nrm, feat, bins, camera, aux, n_contrib, med_local = ctx.state
        P, C = feat.shape
        slots = np.empty((bins.num_pairs, K.G_FIXED + C), feat.dtype)
        with numba.parallel_chunksize(1):
            K.backward(
                bins.tile_start, bins.tile_list, bins.tile_order, bins.box, Tm, opac, nrm, feat, camera.width,
                bins.n_tx, camera.near, camera.far, *aux, n_contrib, med_local,
                _np(g_feat), _np(g_alpha), _np(g_dsum), _np(g_nrm), _np(g_med), _np(g_dist), slots,
            )  # fmt: skip
        grads = np.zeros((P, K.G_FIXED + C), np.float64)
        K.reduce_slots(bins.emit_start, bins.slot_of_emit, slots, grads)
        g = torch.from_numpy(grads.astype(feat.dtype, copy=False))
        return (
            g[:, K.G_T : K.G_T + 9].reshape(P, 3, 3),
            g[:, K.G_OPACITY],
            g[:, K.G_NORMAL : K.G_NORMAL + 3],
            g[:, K.G_FEATURE :],
            None,
            None,
        )


def render(proj: Projected, camera: Camera) -> tuple[list[Tensor], Bins]:
    """Raw maps ``[features, alpha, depth_sum, normal_cam, median, distortion]`` and the bins."""
    bins = make_bins(proj, camera)
    outs = _Rasterize.apply(proj.T, proj.opacities, proj.normals_cam, proj.colors, bins, camera)
    return list(outs), bins
