"""Make the bundled DTU subset from a full scan (run once; the output is committed).

    python scripts/bundle_dtu.py ../shared/data/dtu/scan24 data/raw/dtu/scan24

Keeps the sparse-view input images (23, 24, 33) and every mask and camera (for culling
and held-out checks), all at 800x600 with intrinsics scaled consistently; the 46 other views
at 200x150 in heldout/ (held-out IoU and PSNR).
"""
import sys
from pathlib import Path

from pipeline.config.data import DataConfig
from pipeline.data.heldout import HELDOUT_DIR, write_heldout
from pipeline.data.prepare import prepare_scene

src, dst = Path(sys.argv[1]), Path(sys.argv[2])
prepare_scene(src, dst, DataConfig(views=[23, 24, 33], width=800, height=600), name=dst.name,
              extra_meta={"source": "DTU MVS (NeuS/IDR layout), sparse-view inputs 23/24/33", "units": "world frame in mm"})
# prepare_scene writes the scan afresh, so the held-out views go in afterwards.
write_heldout(src, dst / HELDOUT_DIR, [23, 24, 33], 200, 150)
print(f"wrote {dst} (held-out views at 200x150 in {dst / HELDOUT_DIR})")
