"""The optimize stage (conf/optimize)."""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.params import FromConf, nested_sections, require_in, require_min
from pipeline.errors import ConfigError


@dataclass
class LearningRates(FromConf):
    """Adam learning rates (values: the preset's ``lr``, conf/optimize/*.yaml; 2DGS's rates
    there). ``means`` decays exponentially to ``means_final`` over the run; both are in
    normalised units x ``scene_extent``."""

    SECTION = "optimize.lr"

    means: float
    means_final: float
    log_scales: float
    quats: float
    opacity_logits: float
    sh_dc: float
    sh_rest: float

    def __post_init__(self) -> None:
        # 0 freezes a parameter; a negative rate climbs the loss. ``means`` decays
        # geometrically to ``means_final`` (exp of interpolated logs), so both must be > 0.
        require_min("optimize.lr", self, "means means_final", strict=True)
        require_min("optimize.lr", self, "log_scales quats opacity_logits sh_dc sh_rest")


@dataclass
class DensifyConfig(FromConf):
    """Adaptive density control: the configuration of :class:`pipeline.optimize.strategy.
    DensifyStrategy` (its only one; values: the preset's ``densify``, conf/optimize/*.yaml).
    Iterations are 0-based steps; sizes are relative to ``optimize.scene_extent``."""

    SECTION = "optimize.densify"

    start_iter: int
    stop_iter: int
    every: int
    grad_threshold: float  # mean screen-space gradient, normalised device units (2DGS/3DGS)
    percent_dense: float  # clone if max scale <= this x extent, else split
    split_factor: float  # a split child's scale = parent / split_factor (2DGS: 0.8 * 2)
    prune_opacity: float
    reset_every: int  # opacity reset every this many iterations; 0: never
    reset_value: float  # opacity reset to min(opacity, this)
    max_world_scale: float  # x extent, pruned after the first reset
    max_screen_fraction: float  # x max(W, H), pruned after the first reset (0: off)
    max_surfels: int  # the ceiling of every scene's budget (memory)
    # A scene's budget: this many surfels per object pixel (mean over the input views at the
    # data resolution: mask pixels, or without masks the pixels whose ray crosses the region's
    # sphere), at most max_surfels; 0: max_surfels for every scene (optimize.region).
    surfels_per_object_px: float

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
        for key in ("grad_threshold", "percent_dense", "max_world_scale", "max_screen_fraction", "surfels_per_object_px"):
            if getattr(self, key) < 0:
                raise ConfigError(f"{where}.{key} must be >= 0, got {getattr(self, key)}")


@dataclass
class RegionConfig(FromConf):
    """Where surfels may be (docs/optimize.md "Surfels only where the object is";
    :mod:`pipeline.optimize.region`): inside the sphere of ``sphere_radius`` (normalised
    frame: 1 is the unit sphere of scale_mat, the one the mesh is cut to) and, where masks
    are used, inside every input view's mask grown by ``hull_tolerance_px`` (pixels of the
    data resolution) wherever the centre is in that view's image: the masks' visual hull.
    Init points outside are dropped, densification does not grow there, each refinement and
    the end of training prune what lies outside. ``enabled`` False: no region (values: the
    preset's ``region``, conf/optimize/*.yaml)."""

    SECTION = "optimize.region"

    enabled: bool
    sphere_radius: float
    hull_tolerance_px: float

    def __post_init__(self) -> None:
        require_min("optimize.region", self, "sphere_radius", strict=True)
        require_min("optimize.region", self, "hull_tolerance_px")


@dataclass
class PhotoResetConfig(FromConf):
    """Opacity reset by multi-view photo-consistency (docs/optimize.md "Resetting where the
    views disagree"): after each densification step, every input view is rendered and the
    surfels that are the visible surface (centre projected into the pixel, centre depth
    within ``depth_rel_tol`` of the rendered median depth) of a textured surface pixel whose
    rendered plane has a best-source NCC below ``ncc_min`` get their opacity capped at
    ``opacity``; the next densification step prunes those that have not regained
    ``densify.prune_opacity``. Sources that do not see the point (their rendered depth nearer
    by more than ``depth_rel_tol``) are no evidence. Off unless ``enabled`` (values: the
    preset's ``photo_reset``, conf/optimize/*.yaml)."""

    SECTION = "optimize.photo_reset"

    enabled: bool
    ncc_min: float
    depth_rel_tol: float
    opacity: float

    def __post_init__(self) -> None:
        where = "optimize.photo_reset"
        if not -1 <= self.ncc_min <= 1:
            raise ConfigError(f"{where}.ncc_min must be in [-1, 1], got {self.ncc_min}")
        if self.depth_rel_tol <= 0:
            raise ConfigError(f"{where}.depth_rel_tol must be > 0, got {self.depth_rel_tol}")
        if not 0 < self.opacity < 1:
            raise ConfigError(f"{where}.opacity must be in (0, 1), got {self.opacity}")


@dataclass
class CropConfig(FromConf):
    """Training on part of each view (docs/optimize.md "Training on crops"): an iteration
    renders and back-propagates a window of ``fraction`` x the view's width and height
    (whole pixels), centred on a random mask pixel (a random pixel without masks) and moved
    inside the image; every ``full_every``-th iteration renders the whole view (0: never).
    ``fraction`` 0 or 1: the whole view every iteration (values: the preset's ``crop``,
    conf/optimize/*.yaml)."""

    SECTION = "optimize.crop"

    fraction: float
    full_every: int

    def __post_init__(self) -> None:
        if not 0 <= self.fraction <= 1:
            raise ConfigError(f"optimize.crop.fraction must be in [0, 1], got {self.fraction}")
        if self.full_every < 0:
            raise ConfigError(f"optimize.crop.full_every must be >= 0, got {self.full_every}")

    def active_at(self, it: int) -> bool:
        """Whether iteration ``it`` renders a crop."""
        return 0 < self.fraction < 1 and not (self.full_every > 0 and it % self.full_every == 0)


@dataclass
class TermStarts(FromConf):
    """Iteration from which each loss term is on (0: from the start; values: the preset's
    ``start``, conf/optimize/*.yaml)."""

    SECTION = "optimize.start"

    gcf: int
    nor: int
    d: int
    dn: int
    mv: int  # L_mv, L_mvgeo and L_smooth

    def __post_init__(self) -> None:
        require_min("optimize.start", self, "gcf nor d dn mv")


@dataclass
class OptimizeConfig(FromConf):
    """The optimize stage (values: conf/optimize/*.yaml, the default preset
    conf/optimize/fast.yaml; docs/optimize.md). Training runs in the normalised frame (unit
    sphere of scale_mat); sizes below are in its units."""

    SECTION = "optimize"

    preset: str  # the name of the conf/optimize preset, for reports
    backend: str  # auto (= simd where it builds, else cpu; also on a GPU: resolve_backend) | cpu | simd | cuda | reference
    iterations: int
    seed: int
    sh_degree: int  # the highest SH degree evaluated (0: view-independent colour)
    sh_every: int  # raise the evaluated SH degree by one every this many iterations
    masks: str  # auto (when the scene has masks) | on | off
    background: float  # grey level behind the object (DTU: black)
    init_opacity: float
    init_normals: bool  # seed each surfel's normal from its point normal (False: random, 2DGS)
    init_voxel_norm: float  # thin the init cloud to this voxel before seeding (0: keep every point)
    scene_extent: float  # the object radius in the normalised frame
    # Resolution schedule: [from_fraction_of_iterations, downscale_factor] pairs.
    downscale: list[list[float]]
    surface_alpha: float  # a pixel is surface (for L_gcf, L_nor) where alpha exceeds this
    gcf_max_points: int  # L_gcf on a random subset of at most this many surface pixels (0: all)
    mv_max_points: int  # L_mv on a random subset of at most this many surface pixels (0: all)
    # Draw that subset among the pixels whose reference patch is textured (losses.multiview.textured_pixels):
    # the others give no pair. False: among every surface pixel.
    mv_textured_points: bool
    dn_depth: str  # depth whose normals L_dn compares: median (2DGS DTU) | expected
    near: float  # distortion depth mapping, normalised units (2DGS: 0.2, 100)
    far: float
    checkpoint_every: int  # 0: no checkpoints
    # Adam's (beta1, beta2): its moments average over about 1 / (1 - beta) steps, so a run
    # stretched to k times the steps at 1 / k the learning rates keeps their span with (1 - beta) / k.
    adam_betas: list[float]
    lr: LearningRates
    densify: DensifyConfig
    start: TermStarts
    photo_reset: PhotoResetConfig
    crop: CropConfig
    region: RegionConfig

    BACKENDS = ("auto", "cpu", "simd", "cuda", "reference")

    def __post_init__(self) -> None:
        nested_sections(self, "optimize", lr=LearningRates, densify=DensifyConfig, start=TermStarts,
                        photo_reset=PhotoResetConfig, crop=CropConfig, region=RegionConfig)
        if self.backend not in self.BACKENDS:
            raise ConfigError(f"optimize.backend must be one of {', '.join(self.BACKENDS)}, got {self.backend!r}")
        if self.masks not in ("auto", "on", "off"):
            raise ConfigError(f"optimize.masks must be auto, on or off, got {self.masks!r}")
        if self.dn_depth not in ("median", "expected"):
            raise ConfigError(f"optimize.dn_depth must be median or expected, got {self.dn_depth!r}")
        require_min("optimize", self, "iterations sh_every", 1)
        require_in("optimize", self, "sh_degree", 0, 3)
        require_min("optimize", self, "seed init_voxel_norm gcf_max_points mv_max_points checkpoint_every")
        require_min("optimize", self, "scene_extent", strict=True)
        require_in("optimize", self, "background", 0, 1)
        if not self.downscale or any(len(d) != 2 or not 0 <= d[0] <= 1 or d[1] < 1 for d in self.downscale):
            raise ConfigError(f"optimize.downscale must be [[fraction in 0..1, factor >= 1], ...], got {self.downscale}")
        if sorted(d[0] for d in self.downscale) != [d[0] for d in self.downscale] or self.downscale[0][0] != 0:
            raise ConfigError(f"optimize.downscale must start at fraction 0 and be sorted, got {self.downscale}")
        if len(self.adam_betas) != 2 or not all(isinstance(b, (int, float)) and not isinstance(b, bool) and 0 <= b < 1
                                                for b in self.adam_betas):
            raise ConfigError(f"optimize.adam_betas must be [beta1, beta2], each in [0, 1), got {self.adam_betas}")
        if not 0 < self.init_opacity < 1 or not 0 <= self.surface_alpha < 1 or not 0 < self.near < self.far:
            raise ConfigError("optimize: init_opacity in (0, 1), surface_alpha in [0, 1) and 0 < near < far required")

    def downscale_at(self, it: int) -> int:
        """Downscale factor of iteration ``it``."""
        factor = self.downscale[0][1]
        for frac, f in self.downscale:
            if it >= frac * self.iterations:
                factor = f
        return int(factor)
