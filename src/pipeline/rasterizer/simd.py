"""The ``simd`` backend of :mod:`pipeline.rasterizer`: the ``cpu`` backend with its set-up and
compositing kernels in C++, what ``auto`` picks wherever they build.

The per-surfel set-up and the tile binning are ``_simd.cpp``'s too (:func:`preprocess_all`,
:func:`bin_tiles`: bit for bit the numba kernels' boxes, lists and slots, with one float32 row
per surfel, ``Geometry.surf``, that the compositing reads through the tile lists), the depth sort
a radix sort of its own (:func:`depth_order`); the per-surfel chain rule is the ``cpu``
backend's numba kernel. The forward and backward compositing (~80% of a render at 800x600) take
a tile row of 16 pixels in one vector of float32 lanes, or 8 where an entry's box is at most 8
pixels wide in its tile (docs/rasterizer.md, "The simd kernels"). Float32 input only;
arithmetic is float32 like 2DGS's CUDA kernels, so results match the ``cpu`` backend to float32
rounding, not bit for bit, and a pair at a threshold (``alpha >= 1/255``, the 0.99 cap,
``T > 0.5`` for the median, ``rho3 <= rho2``) can fall on the other side.

The source ships with the package and is compiled on first use by the system's C++ compiler
(``$CXX``, else ``c++``) for the host CPU (``-march=native``). Builds are cached per machine
(compiler version, flags, the CPU's feature flags) in :func:`cache_dirs`' first writable
folder, so a checkout shared by nodes of several CPU types keeps one build per type; a new
source replaces only the same machine's older build. :func:`available` says whether it
built, and why not. One C++ call per thread, from a numba ``prange`` so that numba's OpenMP
threads run them, each taking the next tile (largest first) from a shared counter until none
is left; a tile is one call's sequential pass, so results do not depend on the number of
threads or on which thread renders a tile.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import weakref
from pathlib import Path

import numba
import numba.experimental.function_type  # noqa: F401  (numba's typing of _CFunction arguments)
from numba.extending import typeof_impl
import numpy as np
import torch
from torch import Tensor

from pipeline.rasterizer import _kernels as K
from pipeline.rasterizer import cpu
from pipeline.rasterizer.types import Camera

SOURCE = Path(__file__).with_name("_simd.cpp")
FLAGS = ("-O3", "-march=native", "-ffp-contract=fast", "-fPIC", "-shared", "-std=c++17")
MAX_CHANNELS = 8  # MAXC in _simd.cpp
RMASK_FIELDS = 3  # RM_SIZE in _simd.cpp
RECORD_SLACK = 16  # the kernels store 16 lanes at a tile's last record

_P = ctypes.c_void_p
_I = ctypes.c_int64
_D = ctypes.c_double
_FORWARD_ARGS = [_P, _P, _I, _P, _P, _P, _I, _I, _P, _I, _I, _I, _D, _D, _D] + [_P] * 7 + [_P] * 6 + [_P] * 6
_BACKWARD_ARGS = [_P, _P, _P, _I, _P, _P, _P, _I, _I, _P, _I, _I, _I, _D, _D, _D] + [_P] * 6 + [_P] * 5 + [_P] * 7 + [_P]
_PREPROCESS_ARGS = [_P] * 7 + [_I, _I, _D, _D] + [_P] * 7 + [_I, _P, _I, _P, _I, _I]
_BIN_COUNT_ARGS = [_P, _P, _P, _P, _I, _I, _I, _I, _I, _P, _P, _P, _P]
_BIN_FILL_ARGS = [_P, _P, _P, _P, _I, _P, _P, _I, _I, _I, _I, _P, _P, _P]
_FUNCTIONS = {"simd_forward": _FORWARD_ARGS, "simd_backward": _BACKWARD_ARGS, "simd_preprocess": _PREPROCESS_ARGS,
              "simd_bin_count": _BIN_COUNT_ARGS, "simd_bin_fill": _BIN_FILL_ARGS}

_lock = threading.Lock()
_state: dict[str, object] = {}


class SimdUnavailable(RuntimeError):
    """The C++ kernels could not be built or loaded here (the message says why)."""


def _cpu_flags() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor()


def _compiler() -> str | None:
    return shutil.which(os.environ.get("CXX", "c++"))


def build(compiler: str, flags: tuple[str, ...], out_dir: Path) -> Path:
    """Compile ``_simd.cpp`` with ``compiler`` and ``flags`` into ``out_dir``, return the library.

    Named ``_simd-<machine>-<source>.so``: ``<machine>`` hashes the compiler's version, the
    flags and the CPU's feature flags, ``<source>`` the C++ source. An existing build is
    reused; a new one replaces this machine's builds of other sources only."""
    version = subprocess.run([compiler, "--version"], capture_output=True, text=True, check=False).stdout
    machine = hashlib.sha256(b"\0".join([version.encode(), " ".join(flags).encode(), _cpu_flags().encode()]))
    machine_key, source_key = machine.hexdigest()[:12], hashlib.sha256(SOURCE.read_bytes()).hexdigest()[:12]
    lib = out_dir / f"_simd-{machine_key}-{source_key}.so"
    if lib.exists():
        return lib
    out_dir.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out_dir, suffix=".so.tmp")
    os.close(fd)
    try:
        res = subprocess.run([compiler, *flags, "-o", tmp, str(SOURCE)], capture_output=True, text=True, check=False)
        if res.returncode != 0:
            raise SimdUnavailable(f"{compiler} failed to compile {SOURCE.name}:\n{res.stderr.strip()[-2000:]}")
        os.replace(tmp, lib)  # atomic: a concurrent process sees the whole library or none
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    for old in out_dir.glob(f"_simd-{machine_key}-*.so"):  # a process using one keeps its mapping
        if old != lib:
            old.unlink(missing_ok=True)
    return lib


def cache_dirs() -> list[Path]:
    """Where builds go, first writable wins: ``$GCGS_CACHE_DIR/simd`` if set, ``__pycache__``
    beside this module (a checkout), the user's cache (an installed package), the temp folder."""
    dirs = [Path(os.environ["GCGS_CACHE_DIR"]) / "simd"] if os.environ.get("GCGS_CACHE_DIR") else []
    dirs.append(Path(__file__).with_name("__pycache__"))
    dirs.append(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "gcgs" / "simd")
    dirs.append(Path(tempfile.gettempdir()) / f"gcgs-simd-{os.getuid() if hasattr(os, 'getuid') else 'user'}")
    return dirs


def load(lib_path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(lib_path))
    for name, argtypes in _FUNCTIONS.items():
        getattr(lib, name).argtypes = argtypes
        getattr(lib, name).restype = None
    lib.simd_exp.argtypes = [_P, _P, _I]
    lib.simd_exp.restype = None
    return lib


def library() -> ctypes.CDLL:
    """The compiled kernels (built on first call); raises :class:`SimdUnavailable`."""
    with _lock:
        if "lib" in _state:
            return _state["lib"]  # type: ignore[return-value]
        if "error" in _state:
            raise SimdUnavailable(_state["error"])
        try:
            compiler = _compiler()
            if compiler is None:
                raise SimdUnavailable(f"no C++ compiler ({os.environ.get('CXX', 'c++')!r} not on PATH)")
            if not SOURCE.is_file():
                raise SimdUnavailable(f"the kernels' source {SOURCE} is missing from the installed package")
            lib_path, errors = None, []
            for folder in cache_dirs():
                try:
                    lib_path = build(compiler, FLAGS, folder)
                    break
                except OSError as err:  # not writable here: the next folder
                    errors.append(f"{folder}: {err.strerror or err}")
            if lib_path is None:
                raise SimdUnavailable("no writable folder for the build (" + "; ".join(errors) + ")")
            _state["lib"] = load(lib_path)
        except (SimdUnavailable, OSError) as err:
            _state["error"] = str(err)
            raise SimdUnavailable(str(err)) from None
        return _state["lib"]  # type: ignore[return-value]


def available() -> tuple[bool, str]:
    """``(True, "")`` when the kernels are built and loaded, else ``(False, why)``."""
    try:
        library()
        return True, ""
    except SimdUnavailable as err:
        return False, str(err)


class _CFunction(numba.types.WrapperAddressProtocol):
    """A function of the loaded library as a first-class numba function: its address is an
    argument of the runners below at call time, so numba caches their compiled code on disk
    like the other kernels' (compiling them in each process took ~3 s of every training)."""

    def __init__(self, fn, argtypes: list) -> None:
        numba_type = {_P: numba.types.voidptr, _I: numba.types.int64, _D: numba.types.float64}
        self._address = ctypes.cast(fn, ctypes.c_void_p).value
        self._signature = numba.types.void(*[numba_type[a] for a in argtypes])
        self.numba_type = numba.types.FunctionType(self._signature)

    def __wrapper_address__(self) -> int:
        return self._address

    def signature(self):
        return self._signature


# numba's typeof of a WrapperAddressProtocol builds a new FunctionType at every call of a runner
# (~0.15 ms each, five per render); the kernels' types are fixed.
@typeof_impl.register(_CFunction)
def _typeof_cfunction(val: _CFunction, c) -> numba.types.FunctionType:
    return val.numba_type


def _kernels() -> dict[str, _CFunction]:
    """The library's kernels by name (``simd_forward``, ...), for the runners."""
    with _lock:
        if "kernels" in _state:
            return _state["kernels"]  # type: ignore[return-value]
    lib = library()
    kernels = {name: _CFunction(getattr(lib, name), argtypes) for name, argtypes in _FUNCTIONS.items()}
    with _lock:
        _state["kernels"] = kernels
    return kernels


_PREPROCESS_CHUNK = 2048  # surfels per C++ call of the set-up
_BIN_PARTS = 8  # parts of the depth order binned in parallel (any count gives the same lists)


@numba.njit(parallel=True, cache=True)
def preprocess_all(pre, means, quats, scales, opac, K, Rwc, twc, width, height, near, far, Tm, nrm, depth, box, radii,
                   centre, surf, feat, reached):  # fmt: skip
    """``_kernels.preprocess`` in C++ (float32 surfels), with each surfel's row of ``surf``
    (the compositing kernels' table, its features ``feat`` included) in place of the float64
    ``geo``, and ``reached``: the tiles of its box it reaches, as bits (``_kernels.tile_reached``;
    all set for a box of more than 64 tiles)."""
    P = means.shape[0]
    for c in numba.prange(-(-P // _PREPROCESS_CHUNK)):
        lo = c * _PREPROCESS_CHUNK
        pre(means.ctypes, quats.ctypes, scales.ctypes, opac.ctypes, K.ctypes, Rwc.ctypes, twc.ctypes, width, height,
            near, far, Tm.ctypes, nrm.ctypes, depth.ctypes, box.ctypes, radii.ctypes, centre.ctypes, surf.ctypes,
            surf.shape[1], feat.ctypes, feat.shape[1], reached.ctypes, lo, min(P, lo + _PREPROCESS_CHUNK))  # fmt: skip


@numba.njit(parallel=True, cache=True)
def bin_tiles(count, fill, front_to_back, box, reached, surf, n_tx, n_ty):
    """``_kernels.bin_tiles`` (same outputs, bit for bit) with its two passes in C++, the tiles
    each surfel reaches from :func:`preprocess_all`'s ``reached`` (the rows ``surf`` for boxes of
    more than 64 tiles): they fetch the boxes and bits, read in depth order at scattered ids,
    ahead of use."""
    P = box.shape[0]
    n_tiles = n_tx * n_ty
    n = front_to_back.shape[0]
    per_surfel = np.zeros(P + 1, np.int64)
    tiles = np.empty((n, 4), np.int32)
    part_len = -(-n // _BIN_PARTS)
    counts = np.zeros((_BIN_PARTS, n_tiles), np.int64)
    pixels = np.zeros((_BIN_PARTS, n_tiles), np.int64)
    for b in numba.prange(_BIN_PARTS):
        count(front_to_back.ctypes, box.ctypes, reached.ctypes, surf.ctypes, surf.shape[1], min(n, b * part_len),
              min(n, (b + 1) * part_len), n, n_tx, tiles.ctypes, per_surfel.ctypes, counts[b].ctypes,
              pixels[b].ctypes)  # fmt: skip
    emit_start = np.cumsum(per_surfel)
    tile_start = np.zeros(n_tiles + 1, np.int64)
    capacity = np.zeros(n_tiles + 1, np.int64)
    cursor = np.empty((_BIN_PARTS, n_tiles), np.int64)
    for t in range(n_tiles):
        at = tile_start[t]
        pix = 0
        for b in range(_BIN_PARTS):  # part b's entries of tile t follow the earlier parts'
            cursor[b, t] = at
            at += counts[b, t]
            pix += pixels[b, t]
        tile_start[t + 1] = at
        capacity[t + 1] = capacity[t] + pix
    tile_list = np.empty(tile_start[-1], np.int32)
    slot_of_entry = np.empty(tile_start[-1], np.int64)
    for b in numba.prange(_BIN_PARTS):
        fill(front_to_back.ctypes, box.ctypes, reached.ctypes, surf.ctypes, surf.shape[1], tiles.ctypes, emit_start.ctypes,
             min(n, b * part_len), min(n, (b + 1) * part_len), n, n_tx, cursor[b].ctypes, tile_list.ctypes,
             slot_of_entry.ctypes)  # fmt: skip
    return tile_start, tile_list, emit_start, slot_of_entry, capacity


# The runners make one kernel call per thread on numba's own threads (a second thread pool
# beside numba's spinning OpenMP threads would fight them for the cores), the calls taking
# tiles from one shared counter.
@numba.njit(parallel=True, cache=True)
def forward_all(fwd, n_workers, tile_start, tile_order, tile_list, surf, C, Rwc, W, H, n_tx, near, far, depth_eps,
                m0, m1, m2, m3, m4, m5, m6, a0, a1, a2, a3, a4, med_local, rec_tile_start,
                rec_T, rec_A, rmask, rec_start, rec_count):  # fmt: skip
    next_tile = np.zeros(1, np.int64)
    for _ in numba.prange(n_workers):
        fwd(tile_start.ctypes, tile_order.ctypes, tile_order.shape[0], next_tile.ctypes, tile_list.ctypes,
            surf.ctypes, surf.shape[1], C, Rwc.ctypes, W, H, n_tx, near, far, depth_eps, m0.ctypes, m1.ctypes, m2.ctypes,
            m3.ctypes, m4.ctypes, m5.ctypes, m6.ctypes, a0.ctypes, a1.ctypes, a2.ctypes, a3.ctypes, a4.ctypes,
            med_local.ctypes, rec_tile_start.ctypes, rec_T.ctypes, rec_A.ctypes, rmask.ctypes,
            rec_start.ctypes, rec_count.ctypes)  # fmt: skip


@numba.njit(parallel=True, cache=True)
def backward_all(bwd, n_workers, tile_start, slot_of_entry, tile_order, tile_list, surf, C, Rwc, W, H, n_tx, near, far,
                 depth_eps, a0, a1, a2, a3, a4, med_local, rec_T, rec_A, rmask, rec_start, rec_count,
                 g0, g1, g2, g3, g4, g5, g6, slots):  # fmt: skip
    next_tile = np.zeros(1, np.int64)
    for _ in numba.prange(n_workers):
        bwd(tile_start.ctypes, slot_of_entry.ctypes, tile_order.ctypes, tile_order.shape[0], next_tile.ctypes,
            tile_list.ctypes, surf.ctypes, surf.shape[1], C, Rwc.ctypes, W, H, n_tx, near, far, depth_eps, a0.ctypes, a1.ctypes,
            a2.ctypes, a3.ctypes, a4.ctypes, med_local.ctypes, rec_T.ctypes, rec_A.ctypes, rmask.ctypes,
            rec_start.ctypes, rec_count.ctypes, g0.ctypes, g1.ctypes, g2.ctypes, g3.ctypes, g4.ctypes,
            g5.ctypes, g6.ctypes, slots.ctypes)  # fmt: skip


# Columns of a row of the kernels' table (:func:`preprocess_all`): the entry row's E_FEAT +
# MAX_CHANNELS, whole 64-byte cache lines.
SURF_COLS = -(-(K.E_FEAT + MAX_CHANNELS) // 16) * 16


@numba.njit(cache=True)
def depth_order(depth, radii):
    """``cpu.depth_order`` (the drawn surfels' ids sorted by ``(centre depth, id)``) by a
    radix sort: numpy's sort of 200k doubles takes 11-15 ms on the 2-core machines, this 1-2 ms.

    Three stable passes of 11 bits over the depths rounded to float32 (rounding is monotone,
    so the float64 order holds except inside runs of equal float32 keys), from ids in
    ascending order; then each such run is sorted by ``(depth, id)``: an insertion sort for the
    usual short runs, a stable sort by depth for a long one (ids are ascending in it)."""
    n = 0
    for s in range(radii.shape[0]):
        n += radii[s] > 0
    ids = np.empty(n, np.int64)
    key32 = np.empty(n, np.float32)
    k = 0
    for s in range(radii.shape[0]):
        if radii[s] > 0:
            ids[k] = s
            key32[k] = depth[s]
            k += 1
    keys = key32.view(np.uint32).copy()
    for i in range(n):  # float bits -> unsigned keys in the floats' order
        keys[i] = ~keys[i] if keys[i] >> 31 else keys[i] | np.uint32(0x80000000)
    tmp_k = np.empty_like(keys)
    tmp_i = np.empty_like(ids)
    for shift in (0, 11, 22):
        count = np.zeros(2049, np.int64)
        for i in range(n):
            count[((keys[i] >> shift) & 2047) + 1] += 1
        for b in range(2048):
            count[b + 1] += count[b]
        for i in range(n):
            b = (keys[i] >> shift) & 2047
            tmp_k[count[b]] = keys[i]
            tmp_i[count[b]] = ids[i]
            count[b] += 1
        keys, tmp_k = tmp_k, keys
        ids, tmp_i = tmp_i, ids
    a = 0
    while a < n:
        e = a + 1
        while e < n and keys[e] == keys[a]:
            e += 1
        if e - a > 32:
            run = ids[a:e].copy()
            ids[a:e] = run[np.argsort(depth[run], kind="mergesort")]
        else:
            for i in range(a + 1, e):
                s = ids[i]
                m = i - 1
                while m >= a and (depth[ids[m]] > depth[s] or (depth[ids[m]] == depth[s] and ids[m] > s)):
                    ids[m + 1] = ids[m]
                    m -= 1
                ids[m + 1] = s
        a = e
    return ids


def prepare(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, camera: Camera
) -> cpu.Geometry:
    """:func:`cpu.prepare` in C++ (:func:`preprocess_all`, :func:`bin_tiles`: the same boxes,
    lists and slots bit for bit) with :func:`depth_order`'s radix sort, the kernels' float32
    table ``surf`` (``colors`` in its feature columns) in place of ``geo``, and the tiles in
    one list by decreasing cost (``worker_tiles``; ``worker_start`` is ``[0, n_tiles]``): the
    kernels' calls take the next tile from a shared counter, which balances the threads better
    than ``schedule_tiles``' fixed split (the results are the same: a tile is one call's
    sequential pass). The numba kernels keep their fixed split, which their tests pin bit for
    bit."""
    P = means.shape[0]
    Kc, Rwc, twc = (np.ascontiguousarray(a, np.float64) for a in cpu._camera_arrays(camera))
    Tm, nrm = np.empty((P, 9), np.float32), np.empty((P, 3), np.float32)
    depth, box, radii = np.empty(P, np.float64), np.empty((P, 4), np.int64), np.empty(P, np.int32)
    centre, reached = np.empty((P, 2), np.float32), np.empty(P, np.uint64)
    # The table from the scratch pool, rows on cache lines; back to the pool with the geometry.
    surf_spec = [((P, SURF_COLS), np.float32)]
    surf_buf = cpu.SCRATCH.take("simd-surf", cpu._carve_bytes(surf_spec))
    (surf,) = cpu._carve(surf_buf, surf_spec)
    kernels = _kernels()
    preprocess_all(
        kernels["simd_preprocess"], cpu._np(means), cpu._np(quats), cpu._np(scales), cpu._np(opacities), Kc, Rwc, twc,
        camera.width, camera.height, camera.near, camera.far, Tm, nrm, depth, box, radii, centre, surf,
        cpu._np(colors), reached,
    )  # fmt: skip
    n_tx, n_ty = -(-camera.width // K.TILE), -(-camera.height // K.TILE)
    order = depth_order(depth, radii)
    binned = bin_tiles(kernels["simd_bin_count"], kernels["simd_bin_fill"], order, box, reached, surf, n_tx, n_ty)
    tile_start, tile_list, emit_start, slot_of_entry, rec_tile_start = binned
    cost = np.diff(rec_tile_start).astype(np.float64) + cpu._ENTRY_COST * np.diff(tile_start)
    tile_order = np.argsort(-cost, kind="stable")
    # Room for a whole vector behind each tile's records: the kernels store 16 lanes at a
    # tile's last record, which, in a tile whose pairs fill its region, overwrote the first
    # records of the next tile when that one had been rendered first.
    rec_tile_start = rec_tile_start + RECORD_SLACK * np.arange(rec_tile_start.shape[0])
    geom = cpu.Geometry(
        Tm, nrm, None, depth, box, radii, centre, tile_start, tile_list, emit_start, slot_of_entry, rec_tile_start,
        np.array([0, tile_order.shape[0]]), tile_order, n_tx, surf,
    )  # fmt: skip
    weakref.finalize(geom, cpu.SCRATCH.give, "simd-surf", surf_buf)
    return geom


def _ptr(a: np.ndarray) -> int:
    assert a.flags.c_contiguous, "the kernels read C-contiguous arrays"
    return a.ctypes.data


class SimdCompositor(cpu.Compositor):
    """The C++ set-up and compositing kernels in :class:`cpu.Compositor`'s place: float32 surfel
    rows (``Geometry.surf``) and pair records of their own layout."""

    def prepare(self, means, quats, scales, opacities, colors, camera):
        return prepare(means, quats, scales, opacities, colors, camera)

    def forward(self, ctx, geom, camera, depth_eps, feat):
        H, W = camera.height, camera.width
        C = feat.shape[1]
        _, Rwc, _ = cpu._camera_arrays(camera)
        Rwc = np.ascontiguousarray(Rwc, np.float64)
        f32 = np.float32
        maps = [np.empty((H, W, C), f32)] + [np.empty((H, W), f32) for _ in range(3)]
        maps += [np.empty((H, W, 3), f32), np.empty((H, W, 3), f32), np.empty((H, W), f32)]
        n_rec, n_pairs = int(geom.rec_tile_start[-1]), geom.num_pairs
        specs = [((H, W), np.float64)] * 5 + [((H, W), np.int32)]
        specs += [((n_rec,), f32)] * 2 + [((n_pairs * K.TILE * RMASK_FIELDS,), np.uint16)]
        specs += [((n_pairs,), np.int64), ((n_pairs,), np.int64)]
        scratch = cpu.SCRATCH.take("simd-forward", cpu._carve_bytes(specs))
        weakref.finalize(ctx, cpu.SCRATCH.give, "simd-forward", scratch)
        *aux, med_local, rec_T, rec_A, rmask, rec_start, rec_count = cpu._carve(scratch, specs)
        forward_all(
            _kernels()["simd_forward"], numba.get_num_threads(), geom.tile_start, geom.worker_tiles, geom.tile_list,
            geom.surf, C, Rwc, W, H, geom.n_tx, camera.near, camera.far, depth_eps, *maps, *aux, med_local,
            geom.rec_tile_start, rec_T, rec_A, rmask, rec_start, rec_count,
        )  # fmt: skip
        return maps, (aux, med_local, rec_T, rec_A, rmask, rec_start, rec_count, Rwc)

    def backward(self, geom, camera, depth_eps, feat, state, grads, slots):
        aux, med_local, rec_T, rec_A, rmask, rec_start, rec_count, Rwc = state
        backward_all(
            _kernels()["simd_backward"], numba.get_num_threads(), geom.tile_start, geom.slot_of_entry,
            geom.worker_tiles, geom.tile_list, geom.surf, feat.shape[1], Rwc, camera.width, camera.height, geom.n_tx,
            camera.near, camera.far, depth_eps, *aux, med_local, rec_T, rec_A, rmask, rec_start, rec_count, *grads,
            slots,
        )  # fmt: skip


SIMD = SimdCompositor()


def render(
    means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor, camera: Camera, depth_eps: float
) -> tuple[list[Tensor], Tensor, Tensor, cpu.Geometry]:
    """:func:`cpu.render` with the C++ kernels; float32 tensors, at most
    :data:`MAX_CHANNELS` feature channels. Raises :class:`SimdUnavailable` if they cannot
    be built, ``ValueError`` on other input."""
    reason = unsuited(means, colors)
    if reason:
        raise ValueError(reason)
    library()
    return cpu.render(means, quats, scales, opacities, colors, camera, depth_eps, SIMD)


def unsuited(means: Tensor, colors: Tensor) -> str:
    """Why these surfels cannot go through the simd kernels (``""`` when they can)."""
    if means.dtype != torch.float32 or colors.dtype != torch.float32:
        return f"the simd kernels take float32 surfels, got {means.dtype} / {colors.dtype} (use the cpu backend)"
    if colors.shape[1] > MAX_CHANNELS:
        return f"the simd kernels take at most {MAX_CHANNELS} feature channels, got {colors.shape[1]}"
    return ""


def exp(x: np.ndarray) -> np.ndarray:
    """The kernels' float32 ``exp`` on ``x`` (for its test against ``np.exp``)."""
    x = np.ascontiguousarray(x, np.float32)
    out = np.empty_like(x)
    library().simd_exp(_ptr(x), _ptr(out), x.size)
    return out
