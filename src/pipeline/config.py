"""Typed configs mirroring ``conf/`` and the composed ``params.yaml``.

``conf/`` is the source of truth (Hydra); ``params.yaml`` is its composition, committed
because ``dvc repro`` reads params.yaml without composing. :func:`compose_params`
recomposes ``conf/`` and a test checks that the two agree.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import yaml

from pipeline.errors import ConfigError, MissingInputError

REPO_ROOT = Path(__file__).resolve().parents[2]
CONF_DIR = REPO_ROOT / "conf"
PARAMS_PATH = REPO_ROOT / "params.yaml"

T = TypeVar("T")


@dataclass
class DataConfig:
    """Training views and resolution (conf/data/default.yaml). ``height`` must keep the
    source images' aspect ratio (``gcgs prepare`` refuses to squash)."""

    views: list[int] = field(default_factory=lambda: [23, 24, 33])
    width: int = 800
    height: int = 600

    def __post_init__(self) -> None:
        if not self.views or any(int(v) != v or v < 0 for v in self.views) or len(set(self.views)) != len(self.views):
            raise ConfigError(f"data.views must be distinct view ids >= 0, got {self.views}")
        _check_size("data", self.width, self.height)


@dataclass
class SynthConfig:
    scenes: list[str] = field(default_factory=list)
    seed: int = 0
    width: int = 800
    height: int = 600
    camera_source: str = "data/raw/dtu/scan24"

    def __post_init__(self) -> None:
        _check_size("synth", self.width, self.height)


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


@dataclass
class LossConfig:
    """Loss weights (GCGS paper: lambda_gcf=2, lambda_nor=0.25, lambda_d=10000)."""

    lambda_dssim: float = 0.2
    lambda_gcf: float = 2.0
    lambda_nor: float = 0.25
    lambda_nc: float = 1.0
    lambda_ngc: float = 1.0
    lambda_d: float = 10000.0
    lambda_dn: float = 0.05  # 2DGS depth-normal consistency
    lambda_mask: float = 0.1  # |alpha - mask|, only where masks are used
    gcf_max_dissimilarity: float = 0.5  # L_gcf pairs with 1 - cos at or above this are outliers (FatesGS); 2: none
    # L_mvs: relative L1 of the rendered median depth to the init's MVS depth where it has one
    # (init/NAME/depth/*.npz; 0: off), its weight going linearly to mvs_final x lambda_mvs.
    lambda_mvs: float = 0.0
    mvs_final: float = 1.0
    # L_mv (PGSR): 1 - NCC of grey patches warped by the homography of each pixel's rendered
    # plane into the other input views, at the scene's full resolution, weighted by the
    # forward-backward reprojection (pipeline.mvphoto); lambda_mvgeo weights that reprojection
    # error itself. 0: off.
    lambda_mv: float = 0.0
    lambda_mvgeo: float = 0.0
    mv_patch: int = 7  # NCC patch side, full-resolution pixels (odd)
    mv_min_patch_std: float = 0.01  # grey std below which a patch is flat: no NCC there
    mv_max_fb_px: float = 1.0  # forward-backward reprojection error (training pixels) above which a pair is occluded

    def __post_init__(self) -> None:
        if self.mv_patch < 3 or self.mv_patch % 2 == 0:
            raise ConfigError(f"loss.mv_patch must be odd and >= 3, got {self.mv_patch}")
        if min(self.lambda_mv, self.lambda_mvgeo, self.mv_min_patch_std) < 0 or self.mv_max_fb_px <= 0:
            raise ConfigError("loss.lambda_mv, lambda_mvgeo and mv_min_patch_std must be >= 0 and mv_max_fb_px > 0")
        if self.lambda_mvs < 0 or not 0.0 <= self.mvs_final:
            raise ConfigError(f"loss.lambda_mvs and loss.mvs_final must be >= 0, got {self.lambda_mvs}, {self.mvs_final}")
        if not 0.0 < self.gcf_max_dissimilarity <= 2.0:
            raise ConfigError(f"loss.gcf_max_dissimilarity must be in (0, 2] (1 - cos lies in [0, 2]), "
                              f"got {self.gcf_max_dissimilarity}")


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
    fill_width: int = 200  # width (px) of the absolute-difference sweep where NCC has no match (0: off)
    fill_window: int = 7  # its window side, coarse pixels (odd)
    fill_max_rms: float = 0.05  # its winner's RMS grey difference (object-mean units) above this -> invalid
    fill_min_std: float = 0.002  # its window's grey std (object-mean units) below this -> one grey, invalid
    # A hypothesis scores max(mean NCC over the sources, best source's NCC - this): a point
    # beside an occluding edge is hidden from some sources (>= 2: the mean alone).
    best_source_margin: float = 0.1

    def __post_init__(self) -> None:
        if self.window < 3 or self.window % 2 == 0:
            raise ConfigError(f"init.mvs.window must be odd and >= 3, got {self.window}")
        if self.depth_step_px <= 0 or self.max_depths < 3:
            raise ConfigError("init.mvs: depth_step_px must be > 0 and max_depths >= 3")
        if self.refine_iters < 0 or not 0 < self.refine_step <= self.refine_range:
            raise ConfigError("init.mvs: refine_iters must be >= 0 and 0 < refine_step <= refine_range")
        if self.fill_width < 0 or self.fill_window < 3 or self.fill_window % 2 == 0 or self.fill_max_rms <= 0 \
                or self.fill_min_std < 0:
            raise ConfigError("init.mvs: fill_width must be >= 0, fill_window odd and >= 3, fill_max_rms > 0, fill_min_std >= 0")
        if self.min_rel_std < 0:
            raise ConfigError(f"init.mvs.min_rel_std must be >= 0, got {self.min_rel_std}")
        if not self.best_source_margin >= 0:
            raise ConfigError(f"init.mvs.best_source_margin must be >= 0, got {self.best_source_margin}")


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

    BACKENDS = ("mvs", "sfm", "mast3r", "random")  # pipeline.init.BACKEND_MODULES implements each

    def __post_init__(self) -> None:
        nested_sections(self, "init", mvs=MVSConfig, consistency=ConsistencyConfig, sfm=SfMConfig, mast3r=MASt3RConfig)
        if self.backend not in self.BACKENDS:
            raise ConfigError(f"init.backend must be one of {', '.join(self.BACKENDS)}, got {self.backend!r}")
        if self.voxel_norm < 0:
            raise ConfigError(f"init.voxel_norm must be >= 0, got {self.voxel_norm}")


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
    feature_min_rel_contrast: float = 0.025  # patch grey std / the view's mean grey in its mask below this -> zero feature
    feature_detrend: bool = True  # remove each patch's linear ramp before that test (shading carries no NCC match)
    feature_dtype: str = "float16"  # storage dtype of the feature maps

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


@dataclass
class MeshConfig:
    """TSDF meshing of depth maps (conf/mesh/default.yaml; ``gcgs tsdf``, later ``gcgs mesh``).

    Sizes are in unit-sphere radii (x the scale_mat radius = mm); 2DGS on DTU uses voxel
    0.004 and truncation 0.016. Cleaning keeps every connected component with at least
    ``min_component_fraction`` of the largest one's triangles, so an object in several
    separate parts keeps its parts while small floaters go."""

    voxel_norm: float = 0.004
    trunc_norm: float = 0.016
    min_component_fraction: float = 0.05
    # gcgs mesh (surfels -> depth -> TSDF):
    depth: str = "median"  # rendered depth fused: median (2DGS on DTU) | expected
    alpha_min: float = 0.5  # pixels with less accumulated alpha have no depth
    masks: bool = True  # zero the depth outside the input views' masks (where the scene has masks)
    virtual_per_pair: int = 0  # virtual views rendered between each pair of input views
    # Bounding region for depth fused without masks (meshing/region.py): the unit sphere and,
    # when the depth shows one, the half-space above the support plane (the table).
    region: str = "auto"  # auto (when no mask cuts the fused depth) | on | off
    region_plane_share: float = 0.15  # a plane is the table when at least this share of depth points lie on it
    region_plane_margin_norm: float = 0.008  # the region starts this far above the table (unit-sphere radii)

    def __post_init__(self) -> None:
        if self.region not in ("auto", "on", "off"):
            raise ConfigError(f"mesh.region must be auto, on or off, got {self.region!r}")
        if not 0 < self.region_plane_share <= 1 or self.region_plane_margin_norm < 0:
            raise ConfigError("mesh: region_plane_share must be in (0, 1] and region_plane_margin_norm >= 0")
        if self.depth not in ("median", "expected"):
            raise ConfigError(f"mesh.depth must be median or expected, got {self.depth!r}")
        if not 0 <= self.alpha_min < 1 or self.virtual_per_pair < 0:
            raise ConfigError("mesh: alpha_min must be in [0, 1) and virtual_per_pair >= 0")
        if not 0 < self.voxel_norm < self.trunc_norm:
            raise ConfigError(f"mesh: need 0 < voxel_norm < trunc_norm, got {self.voxel_norm}, {self.trunc_norm}")
        if not 0 <= self.min_component_fraction <= 1:
            raise ConfigError(f"mesh.min_component_fraction must be in [0, 1], got {self.min_component_fraction}")

    def sizes_mm(self, norm_scale_mm: float) -> tuple[float, float]:
        """``(voxel_mm, trunc_mm)`` for a scene whose unit sphere has radius ``norm_scale_mm``."""
        return self.voxel_norm * norm_scale_mm, self.trunc_norm * norm_scale_mm


@dataclass
class LearningRates:
    """Adam learning rates (2DGS defaults). ``means`` decays exponentially to
    ``means_final`` over the run; both are in normalised units x ``scene_extent``."""

    means: float = 1.6e-4
    means_final: float = 1.6e-6
    log_scales: float = 5e-3
    quats: float = 1e-3
    opacity_logits: float = 0.05
    sh_dc: float = 2.5e-3
    sh_rest: float = 1.25e-4  # sh_dc / 20


@dataclass
class DensifyConfig:
    """Adaptive density control: the configuration of :class:`pipeline.optimize.strategy.
    DensifyStrategy` (its only one). Iterations are 0-based steps; sizes are relative to
    ``optimize.scene_extent``."""

    start_iter: int = 500
    stop_iter: int = 15000
    every: int = 100
    grad_threshold: float = 2e-4  # mean screen-space gradient, normalised device units (2DGS/3DGS)
    percent_dense: float = 0.01  # clone if max scale <= this x extent, else split
    split_factor: float = 1.6  # a split child's scale = parent / 1.6 (2DGS: 0.8 * 2)
    prune_opacity: float = 0.05
    reset_every: int = 3000  # 0: never
    reset_value: float = 0.01  # opacity reset to min(opacity, this)
    max_world_scale: float = 0.1  # x extent, pruned after the first reset
    max_screen_fraction: float = 0.0  # x max(W, H), pruned after the first reset (0: off)
    max_surfels: int = 300000  # budget

    def __post_init__(self) -> None:
        where = "optimize.densify"
        if self.every < 1:
            raise ConfigError(f"{where}.every must be >= 1, got {self.every}")
        if not 0 <= self.start_iter <= self.stop_iter:
            raise ConfigError(f"{where}: need 0 <= start_iter <= stop_iter, got {self.start_iter}, {self.stop_iter}")
        if self.reset_every < 0:
            raise ConfigError(f"{where}.reset_every must be >= 0 (0: never), got {self.reset_every}")
        if self.max_surfels < 1:
            raise ConfigError(f"{where}.max_surfels must be >= 1, got {self.max_surfels}")
        if self.split_factor <= 1:
            raise ConfigError(f"{where}.split_factor must be > 1 (children smaller than the parent), "
                              f"got {self.split_factor}")
        if not 0 < self.reset_value < 1:
            raise ConfigError(f"{where}.reset_value must be in (0, 1), got {self.reset_value}")
        if not 0 <= self.prune_opacity < 1:
            raise ConfigError(f"{where}.prune_opacity must be in [0, 1) (0: no pruning), got {self.prune_opacity}")
        for key in ("grad_threshold", "percent_dense", "max_world_scale", "max_screen_fraction"):
            if getattr(self, key) < 0:
                raise ConfigError(f"{where}.{key} must be >= 0, got {getattr(self, key)}")


@dataclass
class TermStarts:
    """Iteration from which each loss term is on (0: from the start)."""

    gcf: int = 0
    nor: int = 0
    d: int = 3000
    dn: int = 7000
    mv: int = 7000  # PGSR starts its multi-view terms at 7000 of 30000


@dataclass
class OptimizeConfig:
    """The optimize stage (conf/optimize/*.yaml, docs/optimize.md). Training runs in the
    normalised frame (unit sphere of scale_mat); sizes below are in its units."""

    preset: str = "custom"  # the name of the conf/optimize preset, for reports
    backend: str = "auto"  # auto (cuda when available, else cpu) | cpu | cuda | reference
    iterations: int = 10000
    seed: int = 0
    sh_degree: int = 3
    sh_every: int = 1000  # raise the evaluated SH degree by one every this many iterations
    masks: str = "auto"  # auto (when the scene has masks) | on | off
    background: float = 0.0  # grey level behind the object (DTU: black)
    init_opacity: float = 0.1
    init_normals: bool = True  # seed each surfel's normal from its point normal (False: random, 2DGS)
    init_voxel_norm: float = 0.0  # thin the init cloud to this voxel before seeding (0: keep every point)
    scene_extent: float = 1.0  # the object radius in the normalised frame
    # Resolution schedule: [from_fraction_of_iterations, downscale_factor] pairs.
    downscale: list[list[float]] = field(default_factory=lambda: [[0.0, 1]])
    surface_alpha: float = 0.5  # a pixel is surface (for L_gcf, L_nor) where alpha exceeds this
    gcf_max_points: int = 16384  # L_gcf on a random subset of at most this many surface pixels (0: all)
    mv_max_points: int = 4096  # L_mv on a random subset of at most this many surface pixels (0: all)
    dn_depth: str = "median"  # depth whose normals L_dn compares: median (2DGS DTU) | expected
    near: float = 0.2  # distortion depth mapping, normalised units (2DGS: 0.2, 100)
    far: float = 100.0
    checkpoint_every: int = 500  # 0: no checkpoints
    lr: LearningRates = field(default_factory=LearningRates)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    start: TermStarts = field(default_factory=TermStarts)

    BACKENDS = ("auto", "cpu", "cuda", "reference")

    def __post_init__(self) -> None:
        nested_sections(self, "optimize", lr=LearningRates, densify=DensifyConfig, start=TermStarts)
        if self.backend not in self.BACKENDS:
            raise ConfigError(f"optimize.backend must be one of {', '.join(self.BACKENDS)}, got {self.backend!r}")
        if self.masks not in ("auto", "on", "off"):
            raise ConfigError(f"optimize.masks must be auto, on or off, got {self.masks!r}")
        if self.dn_depth not in ("median", "expected"):
            raise ConfigError(f"optimize.dn_depth must be median or expected, got {self.dn_depth!r}")
        if self.iterations < 1 or not 0 <= self.sh_degree <= 3 or self.sh_every < 1:
            raise ConfigError("optimize: iterations >= 1, sh_degree in 0..3 and sh_every >= 1 required")
        if not self.downscale or any(len(d) != 2 or not 0 <= d[0] <= 1 or d[1] < 1 for d in self.downscale):
            raise ConfigError(f"optimize.downscale must be [[fraction in 0..1, factor >= 1], ...], got {self.downscale}")
        if sorted(d[0] for d in self.downscale) != [d[0] for d in self.downscale] or self.downscale[0][0] != 0:
            raise ConfigError(f"optimize.downscale must start at fraction 0 and be sorted, got {self.downscale}")
        if not 0 < self.init_opacity < 1 or not 0 <= self.surface_alpha < 1 or not 0 < self.near < self.far:
            raise ConfigError("optimize: init_opacity in (0, 1), surface_alpha in [0, 1) and 0 < near < far required")

    def downscale_at(self, it: int) -> int:
        """Downscale factor of iteration ``it``."""
        factor = self.downscale[0][1]
        for frac, f in self.downscale:
            if it >= frac * self.iterations:
                factor = f
        return int(factor)


@dataclass
class SceneEntry:
    """One entry of ``scenes`` in params.yaml."""

    src: str
    gt: str | None = None


def scene_entry(params: dict, name: str) -> SceneEntry:
    """Scene ``name`` of params ``scenes``; a ConfigError naming the known ones if absent."""
    scenes = params.get("scenes") or {}
    if name not in scenes:
        raise ConfigError(f"scene {name!r} is not in params `scenes` ({sorted(scenes)})")
    return from_dict(SceneEntry, scenes[name], where=f"scenes.{name}")


# Top-level params.yaml sections and their typed configs (``scenes`` maps names to entries).
@dataclass
class VariantConfig:
    """One ablation variant (conf/ablation): where its init cloud comes from and the
    settings it changes, as partial sections merged over params ``optimize``, ``loss`` and
    ``mesh``."""

    INITS = ("mvs", "sfm", "random")

    init: str = "mvs"  # mvs: the init stage's dense cloud; sfm / random: the baseline stage's clouds
    optimize: dict = field(default_factory=dict)
    loss: dict = field(default_factory=dict)
    mesh: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.init not in self.INITS:
            raise ConfigError(f"ablation variant init must be one of {', '.join(self.INITS)}, got {self.init!r}")


@dataclass
class SweepConfig:
    """The speed-accuracy sweep: each cell (a variant) on each scene."""

    scenes: list[str] = field(default_factory=list)
    cells: list[str] = field(default_factory=list)


SEED_REPLICATE = re.compile(r"^(?P<row>.+)_seed(?P<seed>\d+)$")  # Table II's row ROW with training seed K


@dataclass
class AblationConfig:
    """``ablation``: the variants that exist, the ones ``dvc repro`` runs (Table II) and the
    speed-accuracy sweep's cells."""

    run: list[str] = field(default_factory=list)
    variants: dict = field(default_factory=dict)
    speed_accuracy: SweepConfig | dict | None = None

    def __post_init__(self) -> None:
        self.variants = {name: v if isinstance(v, VariantConfig) else from_dict(VariantConfig, v,
                                                                                where=f"ablation.variants.{name}")
                         for name, v in (self.variants or {}).items()}
        nested_sections(self, "ablation", speed_accuracy=SweepConfig)
        for key, names in (("run", self.run), ("speed_accuracy.cells", self.speed_accuracy.cells)):
            missing = sorted(set(names) - set(self.variants))
            if missing:
                raise ConfigError(f"ablation.{key} names undefined variant(s) {missing}; defined: {sorted(self.variants)}")
        for name, v in self.variants.items():
            self._check_seed_replicate(name, v)

    def _check_seed_replicate(self, name: str, v: VariantConfig) -> None:
        """``X_seedK`` is Table II's row X trained with seed K (``full``: the main pipeline):
        it must be X with only ``optimize.seed: K`` added, or its figures would be averaged
        into a row they do not belong to."""
        m = SEED_REPLICATE.match(name)
        if m is None:
            return
        base = VariantConfig() if m["row"] == "full" else self.variants.get(m["row"])
        if base is None:
            raise ConfigError(f"ablation.variants.{name}: a seed replicate of {m['row']!r}, which is not defined")
        expect = dataclasses.replace(base, optimize={**base.optimize, "seed": int(m["seed"])})
        if v != expect:
            raise ConfigError(f"ablation.variants.{name}: a seed replicate must be {m['row']!r} with only "
                              f"optimize.seed: {m['seed']} added, i.e. {dataclasses.asdict(expect)}; got {dataclasses.asdict(v)}")


def losses_in_use(params: dict[str, Any]) -> list[LossConfig]:
    """The loss settings that train on a scene's priors: the main ``loss`` section and each
    variant of ``ablation.run`` merged over it. A prior is needed when any of them weights it."""
    ablation = section(AblationConfig, "ablation", params)
    return [section(LossConfig, "loss", params)] + [merged_section(LossConfig, "loss", params, ablation.variants[n].loss)
                                                    for n in ablation.run]


SECTIONS: dict[str, type] = {
    "data": DataConfig,
    "synth": SynthConfig,
    "evaluate": EvaluateConfig,
    "loss": LossConfig,
    "init": InitConfig,
    "priors": PriorsConfig,
    "mesh": MeshConfig,
    "optimize": OptimizeConfig,
    "ablation": AblationConfig,
}


def _check_size(where: str, width: int, height: int) -> None:
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ConfigError(f"{where}: image size must be positive integers, got {width}x{height}")


def merged_section(cls: type[T], key: str, params: dict[str, Any], changes: dict[str, Any]) -> T:
    """Section ``key`` of ``params`` with the partial mapping ``changes`` merged in
    (nested mappings merge key by key), validated like a params value."""

    def merge(base: dict, extra: dict) -> dict:
        out = copy.deepcopy(base)
        for k, v in extra.items():
            out[k] = merge(out.get(k) or {}, v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
        return out

    return from_dict(cls, merge(params.get(key) or {}, changes or {}), where=f"{key} (with a variant's changes)")


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
    """Build a dataclass from a mapping, rejecting unknown keys (typos fail loudly)."""
    data = dict(data or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown key(s) {unknown} in config section {where or cls.__name__}")
    return cls(**data)


def nested_sections(config: Any, where: str, **classes: type) -> None:
    """Turn the nested sections of ``config`` that are still mappings (as read from YAML)
    into their dataclasses, in place; unknown keys fail as in :func:`from_dict`."""
    for name, cls in classes.items():
        value = getattr(config, name)
        if isinstance(value, dict) or value is None:
            setattr(config, name, from_dict(cls, value, where=f"{where}.{name}"))


def load_params(path: str | Path | None = None) -> dict[str, Any]:
    """Read a params file. Default: ``params.yaml`` of the working directory (DVC runs each
    stage in its project's root), else this repository's."""
    if path is None:
        path = Path("params.yaml") if Path("params.yaml").is_file() else PARAMS_PATH
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: params file not found")
    with open(path) as fh:
        return yaml.safe_load(fh) or {}


def section(cls: type[T], key: str, params: dict[str, Any] | None = None,
            overrides: dict[str, Any] | None = None) -> T:
    """Typed, validated config for one top-level key of params.yaml.

    ``overrides`` (command-line values) maps field names to values, dotted for nested
    sections (``{"mast3r.model": path}``); ``None`` values are not given and leave the
    params value. They are merged into the section's mapping *before* the dataclass is
    built, so an override is validated like a params value and a misspelt name fails."""
    params = load_params() if params is None else params
    data = copy.deepcopy(params.get(key) or {})
    for name, value in (overrides or {}).items():
        if value is None:
            continue
        *parents, leaf = name.split(".")
        node = data
        for parent in parents:
            node = node.setdefault(parent, {})
            if not isinstance(node, dict):
                raise ConfigError(f"{key}.{name}: {parent} is not a section")
        node[leaf] = value
    return from_dict(cls, data, where=key)


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
