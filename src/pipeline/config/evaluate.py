"""The evaluation (conf/evaluate)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from pipeline.errors import ConfigError


@dataclass
class EvaluateConfig:
    cull_views: str = "input"
    mask_dilation_px: float = 24.0
    sample_spacing_mm: float = 0.2
    downsample_radius_mm: float = 0.2
    max_dist_mm: float = 20.0
    patch_mm: float = 60.0

    def __post_init__(self) -> None:
        if self.cull_views not in ("input", "all", "none"):
            raise ConfigError(f"evaluate.cull_views must be input, all or none, got {self.cull_views!r}")
        for key in ("sample_spacing_mm", "downsample_radius_mm", "max_dist_mm"):
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) > 0):
                raise ConfigError(f"evaluate.{key} must be a positive number of mm, got {getattr(self, key)}")
        if not (math.isfinite(self.patch_mm) and self.patch_mm >= 0 and self.mask_dilation_px >= 0):
            raise ConfigError(f"evaluate.patch_mm and mask_dilation_px must be >= 0, got {self.patch_mm}, "
                              f"{self.mask_dilation_px}")
