"""Make the bundled DTU subset from a full scan (run once; the output is committed).

    python scripts/bundle_dtu.py ../shared/data/dtu/scan24 data/raw/dtu/scan24

Keeps the sparse-view input images (23, 24, 33) and every mask and camera (for culling
and held-out checks), all at 800x600 with intrinsics scaled consistently.
"""
import sys
from pathlib import Path

import cv2
import numpy as np

from pipeline import geometry
from pipeline.data import dtu

src, dst = Path(sys.argv[1]), Path(sys.argv[2])
W, H = 800, 600
views = (23, 24, 33)
cams = dtu.load_cameras(src)
scene = dtu.load_scene(src, view_ids=views, resolution=(W, H), with_masks=False)
masks = {}
for v, m in dtu.load_masks(src).items():
    masks[v] = cv2.resize(m.astype(np.float32), (W, H), interpolation=cv2.INTER_AREA) > 0.5
h, w = dtu.read_mask(next((src / "mask").iterdir())).shape
K = {v: geometry.scale_intrinsics(cams.K[v], W / w, H / h) for v in cams.ids}
dtu.write_scene(
    dst,
    images={v: img for v, img in zip(scene.view_ids, scene.images)},
    K=K,
    world_to_cam=cams.world_to_cam,
    norm_to_world=cams.norm_to_world,
    masks=masks,
    meta={"name": dst.name, "scan_id": 24, "source": "DTU MVS scan24 (NeuS/IDR layout), views 23/24/33 at 800x600",
          "units": "world frame in mm"},
)
print(f"wrote {dst}")
