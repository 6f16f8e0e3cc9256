"""Typed configs mirroring ``conf/`` and the composed ``params.yaml``.

``conf/`` is the source of truth (Hydra); ``params.yaml`` is its composition, committed
because ``dvc repro`` reads params.yaml without composing. :func:`compose_params`
recomposes ``conf/`` and a test checks that the two agree.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import yaml

REPO_ROOT = Path(__file__).resolve().parents[2]
CONF_DIR = REPO_ROOT / "conf"
PARAMS_PATH = REPO_ROOT / "params.yaml"

T = TypeVar("T")


@dataclass
class DataConfig:
    views: list[int] = field(default_factory=lambda: [23, 24, 33])
    width: int = 800
    height: int = 600


@dataclass
class SynthConfig:
    scenes: list[str] = field(default_factory=list)
    seed: int = 0
    width: int = 800
    height: int = 600
    camera_source: str = "data/raw/dtu/scan24"


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
            raise ValueError(f"evaluate.cull_views must be input, all or none, got {self.cull_views!r}")


@dataclass
class LossConfig:
    """Loss weights (GCGS paper: lambda_gcf=2, lambda_nor=0.25, lambda_d=10000)."""

    lambda_dssim: float = 0.2
    lambda_gcf: float = 2.0
    lambda_nor: float = 0.25
    lambda_nc: float = 1.0
    lambda_ngc: float = 1.0
    lambda_d: float = 10000.0


@dataclass
class MVSConfig:
    """Plane-sweep MVS (docs/init.md)."""

    depth_step_px: float = 1.0  # plane spacing, pixels of disparity in the widest-baseline source
    max_depths: int = 512  # cap on the number of planes
    window: int = 7  # NCC window side, pixels (odd)
    min_ncc: float = 0.5  # winner's mean NCC below this -> invalid
    min_rel_std: float = 0.025  # reference window grey std / the view's mean grey in its mask below this -> textureless
    sphere_margin: float = 1.0  # depth range: rays crossed with the unit sphere scaled by this
    refine_iters: int = 1  # surface-following refinement passes (0: plain sweep)
    refine_range: float = 2.0  # ... searching +- this many plane steps around the smoothed sweep
    refine_step: float = 0.25  # ... in steps of this fraction of a plane step
    warn_below_matched: float = 0.15  # warn when a view's matched fraction of mask pixels is below this
    warn_below_consistent: float = 0.10  # ... or its geometrically consistent fraction

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"init.mvs.window must be odd and >= 3, got {self.window}")
        if self.depth_step_px <= 0 or self.max_depths < 3:
            raise ValueError("init.mvs: depth_step_px must be > 0 and max_depths >= 3")
        if self.refine_iters < 0 or not 0 < self.refine_step <= self.refine_range:
            raise ValueError("init.mvs: refine_iters must be >= 0 and 0 < refine_step <= refine_range")
        if self.min_rel_std < 0:
            raise ValueError(f"init.mvs.min_rel_std must be >= 0, got {self.min_rel_std}")


@dataclass
class ConsistencyConfig:
    """Geometric consistency of depth maps across views (mvs and mast3r)."""

    px: float = 1.0  # reprojection error bound, pixels
    rel_depth: float = 0.002  # relative depth error bound
    min_views: int = 1  # other views that must agree


@dataclass
class SfMConfig:
    """SIFT matches triangulated with the known cameras."""

    max_features: int = 20000  # per view
    ratio: float = 0.8  # Lowe's ratio test
    epipolar_px: float = 2.0  # distance to the epipolar line from the known cameras, pixels
    reproj_px: float = 2.0  # reprojection error bound after triangulation, pixels
    min_angle_deg: float = 1.0  # triangulation angle lower bound


@dataclass
class MASt3RConfig:
    """MASt3R ONNX backend (contract in docs/init.md)."""

    model: str | None = None  # path of the ONNX file (or --model)
    long_side: int = 512  # network input long side, pixels (dynamic-shape models)
    min_conf: float = 1.5  # MASt3R confidence (>= 1) below this -> invalid
    fit_shift: bool = False  # fit depth = s * pred + t instead of s * pred
    match_subsample: int = 4  # pixel stride for the 3D reciprocal nearest-neighbour matches
    epipolar_px: float = 3.0  # match check against the known epipolar geometry, scene pixels
    consistency_px: float = 2.0  # geometric consistency of the aligned depth maps, pixels
    consistency_rel_depth: float = 0.01  # ... and relative depth
    ransac_iters: int = 200
    inlier_rel: float = 0.01  # RANSAC inlier bound on relative depth error


@dataclass
class InitConfig:
    """The init stage (conf/init/*.yaml)."""

    backend: str = "mvs"
    seed: int = 0
    voxel_norm: float = 0.002  # cloud voxel size, unit-sphere radii (x scale_mat radius = mm)
    normal_knn: int = 20
    random_points: int = 100000  # random backend: points in the unit sphere
    mvs: MVSConfig = field(default_factory=MVSConfig)
    consistency: ConsistencyConfig = field(default_factory=ConsistencyConfig)
    sfm: SfMConfig = field(default_factory=SfMConfig)
    mast3r: MASt3RConfig = field(default_factory=MASt3RConfig)

    BACKENDS = ("mvs", "sfm", "mast3r", "random")

    def __post_init__(self) -> None:
        for name, cls in (("mvs", MVSConfig), ("consistency", ConsistencyConfig), ("sfm", SfMConfig),
                          ("mast3r", MASt3RConfig)):
            value = getattr(self, name)
            if isinstance(value, dict) or value is None:
                setattr(self, name, from_dict(cls, value, where=f"init.{name}"))
        if self.backend not in self.BACKENDS:
            raise ValueError(f"init.backend must be one of {', '.join(self.BACKENDS)}, got {self.backend!r}")
        if self.voxel_norm < 0:
            raise ValueError(f"init.voxel_norm must be >= 0, got {self.voxel_norm}")


@dataclass
class PriorsConfig:
    """The priors stage (conf/priors/default.yaml, docs/priors.md). Backends run only when
    their loss weight is non-zero: features need loss.lambda_gcf > 0, normals loss.lambda_nor > 0."""

    normals: str = "default"  # default (from the init depth maps) | dsine | none
    features: str = "default"  # default (NCC patches) | vismvsnet | none
    dsine_model: str = "models/dsine.onnx"
    vismvsnet_model: str = "models/vismvsnet_features.onnx"
    normal_step_px: int = 2  # central-difference half-width, pixels
    normal_smooth_sigma_px: float = 1.5  # bilateral spatial sigma, pixels (0: no smoothing)
    normal_smooth_sigma_mm: float = 3.0  # bilateral depth sigma, mm
    normal_max_slant_deg: float = 80.0  # steeper depth steps are discontinuities
    feature_patch: int = 5  # odd patch side, 1/2-resolution pixels
    feature_scales: list[int] = field(default_factory=lambda: [1, 2])  # patch dilations
    feature_min_contrast: float = 0.002  # patch grey std (in [0, 1]) below this -> zero feature
    feature_dtype: str = "float16"  # storage dtype of the feature maps

    NORMALS = ("default", "dsine", "none")
    FEATURES = ("default", "vismvsnet", "none")

    def __post_init__(self) -> None:
        if self.normals not in self.NORMALS:
            raise ValueError(f"priors.normals must be one of {', '.join(self.NORMALS)}, got {self.normals!r}")
        if self.features not in self.FEATURES:
            raise ValueError(f"priors.features must be one of {', '.join(self.FEATURES)}, got {self.features!r}")
        if self.normal_step_px < 1 or self.normal_smooth_sigma_px < 0 or self.normal_smooth_sigma_mm <= 0:
            raise ValueError("priors: normal_step_px must be >= 1, normal_smooth_sigma_px >= 0, normal_smooth_sigma_mm > 0")
        if not 0 < self.normal_max_slant_deg < 90:
            raise ValueError(f"priors.normal_max_slant_deg must be in (0, 90), got {self.normal_max_slant_deg}")
        if self.feature_patch < 3 or self.feature_patch % 2 == 0:
            raise ValueError(f"priors.feature_patch must be odd and >= 3, got {self.feature_patch}")
        if not self.feature_scales or any(int(s) != s or s < 1 for s in self.feature_scales):
            raise ValueError(f"priors.feature_scales must be positive integers, got {self.feature_scales}")
        if self.feature_dtype not in ("float16", "float32"):
            raise ValueError(f"priors.feature_dtype must be float16 or float32, got {self.feature_dtype!r}")


@dataclass
class SceneEntry:
    """One entry of ``scenes`` in params.yaml."""

    src: str
    gt: str | None = None


# Top-level params.yaml sections and their typed configs (``scenes`` maps names to entries).
SECTIONS: dict[str, type] = {
    "data": DataConfig,
    "synth": SynthConfig,
    "evaluate": EvaluateConfig,
    "loss": LossConfig,
    "init": InitConfig,
    "priors": PriorsConfig,
}


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
    """Build a dataclass from a mapping, rejecting unknown keys (typos fail loudly)."""
    data = dict(data or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in config section {where or cls.__name__}")
    return cls(**data)


def load_params(path: str | Path | None = None) -> dict[str, Any]:
    """Read a params file. Default: ``params.yaml`` of the working directory (DVC runs each
    stage in its project's root), else this repository's."""
    if path is None:
        path = Path("params.yaml") if Path("params.yaml").is_file() else PARAMS_PATH
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: params file not found")
    with open(path) as fh:
        return yaml.safe_load(fh) or {}


def section(cls: type[T], key: str, params: dict[str, Any] | None = None) -> T:
    """Typed config for one top-level key of params.yaml."""
    params = load_params() if params is None else params
    return from_dict(cls, params.get(key), where=key)


def compose_params(overrides: list[str] | None = None) -> dict[str, Any]:
    """Compose ``conf/config.yaml`` with Hydra's compose API."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=overrides or [])
    return OmegaConf.to_container(cfg, resolve=True)


def dump_params(params: dict[str, Any]) -> str:
    header = "# Generated from conf/ by `gcgs params --write`; do not edit by hand.\n"
    return header + yaml.safe_dump(params, sort_keys=False, default_flow_style=False)
