"""The ``cpu`` backend: one torch.autograd.Function around the numba kernels (the ``simd``
backend shares it, with its own compositing: :class:`Compositor`).

Everything per surfel (ray transform, normal, support box) and per pixel (expected
depth, world normal) is inside the kernels, forward and backward: on a loaded 2-core
machine every small multi-threaded torch op costs up to milliseconds of OpenMP
synchronisation, and the whole render must take ~0.1 s. Only SH colours (when
``sh_degree`` is set) are evaluated in torch before the Function.

Why numba rather than a torch C++/OpenMP extension (both measured 3-8x faster than
pure torch here): it needs no compiler toolchain at install or run time, caches its
machine code next to the module (``cache=True``; first use in a fresh checkout
compiles for about half a minute, later processes load it in about a second), and
specialises the same source for float32 and float64 (float64 is what gradcheck needs).
"""
from __future__ import annotations

import threading
import time
import weakref
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from pipeline.rasterizer import _kernels as K
from pipeline.rasterizer.types import Camera

_compile_seconds: float | None = None
_ENTRY_COST = 8.0  # pixel-pair equivalents of one (tile, surfel) entry's set-up


@dataclass
class Geometry:
    """Per-surfel screen data and the tile binning of one (surfels, camera) pair."""

    Tm: np.ndarray  # (P, 9) ray transforms, row-major, input dtype
    nrm: np.ndarray  # (P, 3) camera-facing normals, input dtype
    geo: np.ndarray | None  # (P, GEO_SIZE) float64, see _kernels.GEO_* (None: the simd backend's ``surf``)
    depth: np.ndarray  # (P,) centre depth
    box: np.ndarray  # (P, 4) int64
    radii: np.ndarray  # (P,) int32
    centre: np.ndarray  # (P, 2) projected centres (pixels), input dtype
    tile_start: np.ndarray
    tile_list: np.ndarray
    emit_start: np.ndarray
    slot_of_entry: np.ndarray
    rec_tile_start: np.ndarray  # each tile's region of the pair-record buffer
    worker_start: np.ndarray  # tiles per thread, balanced by their pixel-surfel pairs
    worker_tiles: np.ndarray
    n_tx: int
    surf: np.ndarray | None = None  # simd backend: (P, simd.SURF_COLS) float32 rows, GEO_* then E_*

    @property
    def num_pairs(self) -> int:
        """(tile, surfel) pairs: the size of the per-pair gradient buffer."""
        return int(self.tile_list.shape[0])

    @property
    def box_pixels(self) -> int:
        """Pixel-surfel pairs inside the support boxes (the pairs the kernels visit)."""
        vis = self.radii > 0
        b = self.box[vis]
        return int(((b[:, 1] - b[:, 0] + 1) * (b[:, 3] - b[:, 2] + 1)).sum())


class ScratchPool:
    """Large scratch buffers of recent renders, kept for reuse.

    Why: the forward's pair records (tens to hundreds of MB) and the backward's gradient
    slots are written once per render; a fresh allocation is page-faulted in by the
    kernel threads on first touch, which cost ~20 ms of a ~60 ms forward at 400x300 /
    50k surfels (measured), while reused pages are already mapped. A render takes a
    buffer, and gives it back when its autograd context is freed (after backward, or at
    once under ``no_grad``); a graph that is still alive keeps its buffer, so nothing is
    ever shared. At most ``keep`` idle buffers are held; ``clear()`` drops them.
    """

    def __init__(self, keep: int = 2) -> None:
        self.keep = keep
        self._idle: dict[str, list[np.ndarray]] = {}
        self._lock = threading.Lock()

    def take(self, role: str, nbytes: int) -> np.ndarray:
        """A uint8 buffer of at least ``nbytes`` for ``role`` (the smallest idle one that fits)."""
        with self._lock:
            idle = self._idle.setdefault(role, [])
            fits = [b for b in idle if b.nbytes >= nbytes]
            if fits:
                buf = min(fits, key=lambda b: b.nbytes)
                idle[:] = [b for b in idle if b is not buf]
                return buf
        return np.empty(int(nbytes * 1.25) + 64, np.uint8)  # headroom: scenes grow while training

    def give(self, role: str, buf: np.ndarray) -> None:
        with self._lock:
            idle = self._idle.setdefault(role, [])
            idle.append(buf)
            idle.sort(key=lambda b: -b.nbytes)
            del idle[self.keep :]

    def clear(self) -> None:
        with self._lock:
            self._idle = {}

    @property
    def idle_bytes(self) -> int:
        return sum(b.nbytes for idle in self._idle.values() for b in idle)


SCRATCH = ScratchPool()


def _carve(buf: np.ndarray, specs: list[tuple[tuple[int, ...], type]]) -> list[np.ndarray]:
    """Views of ``buf`` with the given shapes and dtypes, each 64-byte aligned."""
    views, off = [], (-buf.ctypes.data) % 64
    for shape, dtype in specs:
        n = int(np.prod(shape)) * np.dtype(dtype).itemsize
        views.append(buf[off : off + n].view(dtype).reshape(shape))
        off += n + (-n) % 64
    return views


def _carve_bytes(specs: list[tuple[tuple[int, ...], type]]) -> int:
    return 64 + sum(int(np.prod(sh)) * np.dtype(dt).itemsize + 64 for sh, dt in specs)


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def _camera_arrays(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w2c = camera.world_to_cam.numpy()
    return camera.K.numpy(), np.ascontiguousarray(w2c[:3, :3]), np.ascontiguousarray(w2c[:3, 3])


def depth_order(depth: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """The drawn surfels' ids sorted by ``(centre depth, id)``. numpy's quicksort
    (vectorised; 2.5 ms for 200k against 9 ms of per-tile merge sorts on 2 threads),
    then ties broken by id, so the order is the one a stable sort gives."""
    visible = np.flatnonzero(radii > 0)
    order = visible[np.argsort(depth[visible], kind="quicksort")]
    K.break_depth_ties(order, depth)
    return order


def prepare(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, camera: Camera) -> Geometry:
    """Per-surfel set-up and tile binning (no gradient)."""
    P = means.shape[0]
    dtype = np.float64 if means.dtype == torch.float64 else np.float32
    Kc, Rwc, twc = _camera_arrays(camera)
    Tm = np.empty((P, 9), dtype)
    nrm = np.empty((P, 3), dtype)
    geo = np.empty((P, K.GEO_SIZE), np.float64)
    depth = np.empty(P, np.float64)
    box = np.empty((P, 4), np.int64)
    radii = np.empty(P, np.int32)
    centre = np.empty((P, 2), dtype)
    reached = np.empty(P, np.uint64)
    # round32: the binning's test on geo as the simd kernels' float32 rows hold it, so both
    # backends list alike
    round32 = dtype == np.float32
    K.preprocess(
        _np(means), _np(quats), _np(scales), _np(opacities), Kc, Rwc, twc, camera.width, camera.height,
        camera.near, camera.far, Tm, nrm, geo, depth, box, radii, centre, round32, reached,
    )  # fmt: skip
    n_tx = -(-camera.width // K.TILE)
    n_ty = -(-camera.height // K.TILE)
    binned = K.bin_tiles(depth_order(depth, radii), box, reached, geo, round32, n_tx, n_ty)
    tile_start, tile_list, emit_start, slot_of_entry, rec_tile_start = binned
    # Cost of a tile ~ its pixel-surfel pairs plus a per-surfel set-up.
    cost = np.diff(rec_tile_start).astype(np.float64) + _ENTRY_COST * np.diff(tile_start)
    worker_start, worker_tiles = K.schedule_tiles(cost, numba.get_num_threads())
    return Geometry(
        Tm, nrm, geo, depth, box, radii, centre, tile_start, tile_list, emit_start, slot_of_entry, rec_tile_start,
        worker_start, worker_tiles, n_tx,
    )  # fmt: skip


class Compositor:
    """The forward and backward compositing of a render, the part of a CPU backend that
    differs: :class:`NumbaCompositor` (``cpu``) and ``simd.SimdCompositor`` (``simd``). The
    set-up, the autograd Function and the per-surfel chain rule are shared."""

    def prepare(
        self, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, camera: Camera
    ) -> Geometry:
        """Set-up and tile binning (``colors``: what the forward will composite, for a backend
        that stores them with the surfels' screen data)."""
        raise NotImplementedError

    def forward(self, ctx, geom: Geometry, camera: Camera, depth_eps: float, feat: np.ndarray) -> tuple[list[np.ndarray], tuple]:
        """The seven maps, and what :meth:`backward` needs (its scratch given back when
        ``ctx`` is freed)."""
        raise NotImplementedError

    def backward(self, geom: Geometry, camera: Camera, depth_eps: float, feat: np.ndarray, state: tuple,
                 grads: list[np.ndarray], slots: np.ndarray) -> None:  # fmt: skip
        """Fill ``slots``, one row of gradient sums per (tile, surfel) pair."""
        raise NotImplementedError


class NumbaCompositor(Compositor):
    def prepare(self, means, quats, scales, opacities, colors, camera):
        return prepare(means, quats, scales, opacities, camera)

    def forward(self, ctx, geom, camera, depth_eps, feat):
        H, W = camera.height, camera.width
        C = feat.shape[1]
        dtype = geom.Tm.dtype
        _, Rwc, _ = _camera_arrays(camera)
        maps = [np.empty((H, W, C), dtype)] + [np.empty((H, W), dtype) for _ in range(3)]
        maps += [np.empty((H, W, 3), dtype), np.empty((H, W, 3), dtype), np.empty((H, W), dtype)]
        # Kept for the backward: per-pixel state, and the pair records sized by the boxes'
        # pixel count (an upper bound; only the pages of used records are touched).
        specs = [((H, W), np.float64)] * 5 + [((H, W), np.int32)]
        n_rec, n_pairs = int(geom.rec_tile_start[-1]), geom.num_pairs
        specs += [((n_rec, K.R_SIZE), dtype), ((n_pairs,), np.int64), ((n_pairs,), np.int64)]
        specs += [((n_pairs, K.E_FEAT + C), np.float64)]
        scratch = SCRATCH.take("forward", _carve_bytes(specs))
        weakref.finalize(ctx, SCRATCH.give, "forward", scratch)
        *aux, med_local, rec, rec_start, rec_count, ent = _carve(scratch, specs)
        K.gather_entries(geom.tile_list, geom.geo, geom.Tm, geom.nrm, geom.box, feat, ent)
        K.forward(
            geom.tile_start, geom.worker_start, geom.worker_tiles, ent, Rwc, W, geom.n_tx, camera.near, camera.far,
            depth_eps, *maps, *aux, med_local, geom.rec_tile_start, rec, rec_start, rec_count,
        )  # fmt: skip
        return maps, (aux, med_local, rec, rec_start, rec_count, ent)

    def backward(self, geom, camera, depth_eps, feat, state, grads, slots):
        aux, med_local, rec, rec_start, rec_count, ent = state
        _, Rwc, _ = _camera_arrays(camera)
        K.backward(
            geom.tile_start, geom.slot_of_entry, geom.worker_start, geom.worker_tiles, ent, Rwc, camera.width,
            geom.n_tx, camera.near, camera.far, depth_eps, *aux, med_local, rec, rec_start, rec_count, *grads, slots,
        )  # fmt: skip


NUMBA = NumbaCompositor()


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, means2d, geom: Geometry, camera: Camera, depth_eps: float,
                compositor: Compositor):  # fmt: skip
        feat = _np(colors)
        maps, state = compositor.forward(ctx, geom, camera, depth_eps, feat)
        ctx.state = (geom, camera, depth_eps, feat, state, compositor)
        ctx.save_for_backward(means, quats, scales)
        return tuple(torch.from_numpy(a) for a in maps)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, *grads):
        geom, camera, depth_eps, feat, state, compositor = ctx.state
        means, quats, scales = ctx.saved_tensors
        P, C = feat.shape
        Kc, Rwc, _ = _camera_arrays(camera)
        slot_spec = [((geom.num_pairs, K.S_FIXED + C), np.float64)]
        slot_buf = SCRATCH.take("backward", _carve_bytes(slot_spec))
        (slots,) = _carve(slot_buf, slot_spec)
        compositor.backward(geom, camera, depth_eps, feat, state, [_np(g) for g in grads], slots)
        dtype = geom.Tm.dtype
        # Every row is written by the kernel (zeros for surfels never drawn).
        out = [np.empty((P, 3), dtype), np.empty((P, 4), dtype), np.empty((P, 2), dtype), np.empty(P, dtype)]
        out += [np.empty((P, C), dtype), np.empty((P, 2), dtype)]
        K.reduce_and_chain(
            geom.emit_start, slots, _np(quats), _np(scales), _np(means), geom.Tm, geom.nrm, Kc, Rwc, *out
        )
        SCRATCH.give("backward", slot_buf)
        return tuple(torch.from_numpy(a) for a in out) + (None, None, None, None)


def render(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, camera: Camera, depth_eps: float,
    compositor: Compositor = NUMBA,
) -> tuple[list[Tensor], Tensor, Tensor, Geometry]:
    """Maps ``[features, alpha, depth_expected, depth_median, normal_cam, normal_world,
    distortion]``, ``radii``, ``means2d`` and the geometry (for statistics)."""
    geom = compositor.prepare(means, quats, scales, opacities, colors, camera)
    means2d = torch.from_numpy(geom.centre).requires_grad_(torch.is_grad_enabled())
    maps = _Rasterize.apply(means, quats, scales, opacities, colors, means2d, geom, camera, depth_eps, compositor)
    return list(maps), torch.from_numpy(geom.radii), means2d, geom


def warm_up() -> float:
    """Compile (or load from numba's cache) every kernel for float32 and float64 on a
    tiny scene; returns the seconds this took (0 if already done in this process)."""
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
