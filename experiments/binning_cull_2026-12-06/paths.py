"""paths.py: which branch of ``_kernels.tile_reached`` decides the benchmark's entries
(800x600 / 200k): boxes in one tile (untested), the low-pass disc, the ellipse's centre in the
rectangle, the edges (kept or dropped), and the surfels whose ellipse centre is
ill-conditioned. Run from the repository root with the venv on."""
import sys
from pathlib import Path

import numba
import numpy as np

sys.argv = ["x", "none"]
exec(open(Path(__file__).resolve().parent.parent / "setup_simd_2026-12-06" / "harness.py").read().split("mode = sys.argv[1]")[0])
from pipeline.rasterizer import _kernels as K
from pipeline.rasterizer import simd

s, cam = case(800, 600, 200000, 3)
g = simd.prepare(s.means, s.quats, s.scales, s.opacities, s.features, cam)


@numba.njit
def paths(box, radii, surf):
    st = np.zeros(8, np.int64)
    for i in range(box.shape[0]):
        if radii[i] == 0:
            continue
        b = box[i]
        st[0] += 1
        if b[0] // 16 == b[1] // 16 and b[2] // 16 == b[3] // 16:
            st[1] += 1
            continue
        c = K.tile_conic(surf[i], False)
        st[7] += not c[20]
        for ty in range(b[2] // 16, b[3] // 16 + 1):
            for tx in range(b[0] // 16, b[1] // 16 + 1):
                xa, xb = max(b[0], tx * 16), min(b[1], tx * 16 + 15)
                ya, yb = max(b[2], ty * 16), min(b[3], ty * 16 + 15)
                st[2] += 1
                dx = max(max(xa - c[10], 0.0), c[10] - xb)
                dy = max(max(ya - c[11], 0.0), c[11] - yb)
                if 2.0 * (dx * dx + dy * dy) <= c[9]:
                    st[3] += 1
                elif xa <= c[17] <= xb and ya <= c[18] <= yb:
                    st[4] += 1
                elif K.tile_reached(c, float(xa), float(xb), float(ya), float(yb)):
                    st[5] += 1
                else:
                    st[6] += 1
    return st


names = ["drawn surfels", "boxes in one tile", "entries of larger boxes", "kept by the disc",
         "kept by the ellipse's centre", "kept by an edge", "dropped", "surfels ill-conditioned"]
for n, v in zip(names, paths(g.box, g.radii, g.surf)):
    print(f"{n:30s} {v}")
