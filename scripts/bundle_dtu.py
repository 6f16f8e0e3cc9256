"""Make the bundled DTU subset from a full scan (run once; the output is committed).

    python scripts/bundle_dtu.py ../shared/data/dtu/scan24 data/raw/dtu/scan24

Keeps the sparse-view input images (23, 24, 33) and every mask and camera (for culling
and held-out checks), all at 800x600 with intrinsics scaled consistently.
"""
import sys
from pathlib import Path

from pipeline.config import DataConfig
from pipeline.data.prepare import prepare_scene

src, dst = Path(sys.argv[1]), Path(sys.argv[2])
prepare_scene(src, dst, DataConfig(views=[23, 24, 33], width=800, height=600), name=dst.name,
              extra_meta={"source": "DTU MVS (NeuS/IDR layout), sparse-view inputs 23/24/33", "units": "world frame in mm"})
print(f"wrote {dst}")
