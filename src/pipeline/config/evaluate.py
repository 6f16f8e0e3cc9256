"""The evaluation (conf/evaluate)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from pipeline.config.params import FromConf
from pipeline.errors import ConfigError


@dataclass
class EvaluateConfig(FromConf):
    """The DTU Chamfer protocol (values: conf/evaluate/default.yaml)."""

    SECTION = "evaluate"

    cull_views: str  # input | all | none: the views whose masks cull the mesh before sampling
    mask_dilation_px: float  # mask dilation disk radius at 1600x1200, scaled to the mask resolution
    sample_spacing_mm: float  # triangle sampling step
    downsample_radius_mm: float  # radius downsampling of the sampled points
    max_dist_mm: float  # distances >= this are left out of the means
    patch_mm: float  # bounding-box margin

    def __post_init__(self) -> None:
        if self.cull_views not in ("input", "all", "none"):
            raise ConfigError(f"evaluate.cull_views must be input, all or none, got {self.cull_views!r}")
        for key in ("sample_spacing_mm", "downsample_radius_mm", "max_dist_mm"):
            if not (math.isfinite(getattr(self, key)) and getattr(self, key) > 0):
                raise ConfigError(f"evaluate.{key} must be a positive number of mm, got {getattr(self, key)}")
        if not (math.isfinite(self.patch_mm) and self.patch_mm >= 0 and self.mask_dilation_px >= 0):
            raise ConfigError(f"evaluate.patch_mm and mask_dilation_px must be >= 0, got {self.patch_mm}, "
                              f"{self.mask_dilation_px}")
