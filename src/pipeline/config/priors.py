"""The priors stage (conf/priors)."""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.params import FromConf
from pipeline.errors import ConfigError


@dataclass
class PriorsConfig(FromConf):
    """The priors stage (values: conf/priors/default.yaml; docs/priors.md). Backends run only
    when their loss weight is non-zero: features need loss.lambda_gcf > 0, normals loss.lambda_nor > 0."""

    SECTION = "priors"

    normals: str  # default (from the init depth maps) | dsine | none
    features: str  # default (NCC patches) | vismvsnet | none
    dsine_model: str  # path of the DSINE ONNX file
    vismvsnet_model: str  # path of the Vis-MVSNet feature ONNX file
    normal_step_px: int  # central-difference half-width, pixels
    normal_smooth_sigma_px: float  # bilateral spatial sigma, pixels (0: no smoothing)
    normal_smooth_sigma_mm: float  # bilateral depth sigma, mm
    normal_max_slant_deg: float  # steeper depth steps are discontinuities
    feature_patch: int  # odd patch side, 1/2-resolution pixels
    feature_scales: list[int]  # patch dilations
    feature_min_rel_contrast: float  # patch grey std / the view's mean grey in its mask below this -> zero feature
    feature_detrend: bool  # remove each patch's linear ramp before that test (shading carries no NCC match)
    feature_dtype: str  # storage dtype of the feature maps: float16 | float32

    NORMALS = ("default", "dsine", "none")
    FEATURES = ("default", "vismvsnet", "none")

    def __post_init__(self) -> None:
        if self.normals not in self.NORMALS:
            raise ConfigError(f"priors.normals must be one of {', '.join(self.NORMALS)}, got {self.normals!r}")
        if self.features not in self.FEATURES:
            raise ConfigError(f"priors.features must be one of {', '.join(self.FEATURES)}, got {self.features!r}")
        if self.normal_step_px < 1 or self.normal_smooth_sigma_px < 0 or self.normal_smooth_sigma_mm <= 0:
            raise ConfigError("priors: normal_step_px must be >= 1, normal_smooth_sigma_px >= 0, normal_smooth_sigma_mm > 0")
        if not 0 < self.normal_max_slant_deg < 90:
            raise ConfigError(f"priors.normal_max_slant_deg must be in (0, 90), got {self.normal_max_slant_deg}")
        if self.feature_patch < 3 or self.feature_patch % 2 == 0:
            raise ConfigError(f"priors.feature_patch must be odd and >= 3, got {self.feature_patch}")
        if not self.feature_scales or any(int(s) != s or s < 1 for s in self.feature_scales):
            raise ConfigError(f"priors.feature_scales must be positive integers, got {self.feature_scales}")
        if self.feature_dtype not in ("float16", "float32"):
            raise ConfigError(f"priors.feature_dtype must be float16 or float32, got {self.feature_dtype!r}")
