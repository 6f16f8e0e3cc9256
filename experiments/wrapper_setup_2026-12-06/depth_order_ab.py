import sys, time, statistics, pathlib; sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import numpy as np
from depth_order_parallel import depth_order_par
from depth_order_two_pass import depth_order2
from pipeline.rasterizer import simd, cpu
rng = np.random.default_rng(0)
for P in (0, 1, 5, 1000, 200_000):
    depth = rng.uniform(500, 900, P)
    if P > 10: depth[::7] = depth[3]  # ties
    radii = (rng.random(P) > 0.1).astype(np.int32)
    a, c = simd.depth_order(depth, radii), cpu.depth_order(depth, radii)
    for f in (depth_order_par, depth_order2):
        assert np.array_equal(a, f(depth, radii)) and np.array_equal(a, c), P
depth = rng.uniform(500, 900, 200_000); radii = np.ones(200_000, np.int32)
for f in (simd.depth_order, depth_order_par, depth_order2) * 2:
    ts = []
    for _ in range(20):
        t = time.perf_counter(); f(depth, radii); ts.append(time.perf_counter() - t)
    print(f.__name__ if hasattr(f, '__name__') else f, "%.2f ms" % (statistics.median(ts) * 1e3))
