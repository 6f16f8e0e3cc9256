"""The C++ prototype of ``_kernels.preprocess`` (``preprocess.cpp``) against the numba kernel:
bit for bit on the benchmark's scenes and on random surfels, then timed on 800x600 / 200k
surfels with one thread and with two (numba's prange against two Python threads, each a
ctypes call on half the surfels).

    g++ -O3 -march=native -ffp-contract=fast -fno-math-errno -fPIC -shared -std=c++17 \\
        -o /tmp/preprocess.so experiments/setup_simd_2026-12-06/preprocess.cpp
    python experiments/setup_simd_2026-12-06/compare.py /tmp/preprocess.so
"""
import ctypes
import statistics
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np
import torch

from pipeline.benchmarks.surfel_scenes import dtu_camera, object_surfels
from pipeline.rasterizer import _kernels as K
from pipeline.rasterizer import cpu

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "rasterizer"))
from raster_helpers import random_camera, random_surfels  # noqa: E402

lib = ctypes.CDLL(sys.argv[1])
_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
lib.simd_preprocess.argtypes = [_P] * 7 + [_I, _I, _D, _D] + [_P] * 7 + [_I, _I]


def outputs(P):
    return [np.empty((P, 9), np.float32), np.empty((P, 3), np.float32), np.empty((P, K.GEO_SIZE)), np.empty(P),
            np.empty((P, 4), np.int64), np.empty(P, np.int32), np.empty((P, 2), np.float32)]


def inputs(s, cam):
    arrays = [np.ascontiguousarray(cpu._np(t.detach())) for t in (s.means, s.quats, s.scales, s.opacities)]
    arrays += [np.ascontiguousarray(a, np.float64) for a in cpu._camera_arrays(cam)]
    return arrays


def run_numba(arrays, cam, out):
    K.preprocess(*arrays, cam.width, cam.height, cam.near, cam.far, *out)


def run_cpp(arrays, cam, out, lo, hi):
    ptrs = [a.ctypes.data for a in arrays]
    lib.simd_preprocess(*ptrs, cam.width, cam.height, cam.near, cam.far, *[a.ctypes.data for a in out], lo, hi)


def same(a, b):
    return all(np.array_equal(x.view(np.uint8), y.view(np.uint8)) for x, y in zip(a, b))


scenes = []
for W, H, N in [(800, 600, 200_000), (400, 300, 50_000), (123, 77, 3000)]:
    cam, n2w = dtu_camera(W, H)
    scenes.append((f"object {W}x{H} / {N}", object_surfels(N, n2w, seed=0), cam))
for seed in range(4):
    cam = random_camera(64, 48, seed)
    scenes.append((f"random {seed}", random_surfels(500, cam, 3, seed, torch.float32, scale=(1e-6, 3.0)), cam))
for name, s, cam in scenes:
    arrays, P = inputs(s, cam), s.means.shape[0]
    a, b = outputs(P), outputs(P)
    run_numba(arrays, cam, a)
    run_cpp(arrays, cam, b, 0, P)
    print(name, "bit for bit" if same(a, b) else "DIFFERENT")

name, s, cam = scenes[0]
arrays, P = inputs(s, cam), s.means.shape[0]
a, b = outputs(P), outputs(P)
pool = ThreadPoolExecutor(2)
mid = P // 2 // 8 * 8


def median_ms(fn, reps=21):
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts) * 1e3


for threads in (1, 2):
    numba.set_num_threads(threads)
    cpp = (lambda: run_cpp(arrays, cam, b, 0, P)) if threads == 1 else \
        (lambda: list(pool.map(lambda r: run_cpp(arrays, cam, b, *r), [(0, mid), (mid, P)])))
    for _ in range(2):
        print(f"{threads} thread(s): numba {median_ms(lambda: run_numba(arrays, cam, a)):.2f} ms, "
              f"C++ {median_ms(cpp):.2f} ms")
print("two threads bit for bit:", same(a, b))
