"""The init stage (conf/init)."""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.params import FromConf, nested_sections, require_in, require_min
from pipeline.errors import ConfigError


@dataclass
class MVSConfig(FromConf):
    """Plane-sweep MVS (docs/init.md)."""

    SECTION = "init.mvs"

    depth_step_px: float  # plane spacing, pixels of disparity in the widest-baseline source
    max_depths: int  # cap on the number of planes
    window: int  # NCC window side, pixels (odd)
    min_ncc: float  # winner's mean NCC below this -> invalid
    min_rel_std: float  # reference window grey std / the view's mean grey in its mask below this -> textureless
    sphere_margin: float  # depth range: rays crossed with the unit sphere scaled by this
    refine_iters: int  # surface-following refinement passes (0: plain sweep)
    refine_range: float  # ... searching +- this many plane steps around the smoothed sweep
    refine_step: float  # ... in steps of this fraction of a plane step
    warn_below_matched: float  # warn when a view's matched fraction of mask pixels is below this
    warn_below_consistent: float  # ... or its geometrically consistent fraction
    fill_width: int  # width (px) of the absolute-difference sweep where NCC has no match (0: off)
    fill_window: int  # its window side, coarse pixels (odd)
    fill_max_rms: float  # its winner's RMS grey difference (object-mean units) above this -> invalid
    fill_min_std: float  # its window's grey std (object-mean units) below this -> one grey, invalid
    # A hypothesis scores max(mean NCC over the sources, best source's NCC - this): a point
    # beside an occluding edge is hidden from some sources (>= 2: the mean alone).
    best_source_margin: float
    # Holes of the consistent depth that good depth encloses, up to this fraction of the image's
    # pixels, are filled by harmonic interpolation and their points join the cloud (not the depth
    # maps, which stay two-view-confirmed); 0: off. pipeline.init.hole_fill.
    hole_fill_area: float
    hole_fill_max_bend: float  # ... only where the points around it lie within this x its extent of a plane

    def __post_init__(self) -> None:
        if not 0 <= self.hole_fill_area < 1 or not self.hole_fill_max_bend >= 0:
            raise ConfigError(f"init.mvs.hole_fill_area must be in [0, 1) and hole_fill_max_bend >= 0, got "
                              f"{self.hole_fill_area} and {self.hole_fill_max_bend}")
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
        require_in("init.mvs", self, "min_ncc", -1, 1)
        require_in("init.mvs", self, "warn_below_matched warn_below_consistent", 0, 1)
        require_min("init.mvs", self, "sphere_margin", strict=True)


@dataclass
class ConsistencyConfig(FromConf):
    """Geometric consistency of depth maps across views (mvs and mast3r)."""

    SECTION = "init.consistency"

    px: float  # reprojection error bound, pixels
    rel_depth: float  # relative depth error bound
    min_views: int  # other views that must agree

    def __post_init__(self) -> None:
        require_min("init.consistency", self, "px rel_depth", strict=True)
        require_min("init.consistency", self, "min_views")


@dataclass
class SfMConfig(FromConf):
    """SIFT matches triangulated with the known cameras."""

    SECTION = "init.sfm"

    max_features: int  # per view
    ratio: float  # Lowe's ratio test
    epipolar_px: float  # distance to the epipolar line from the known cameras, pixels
    reproj_px: float  # reprojection error bound after triangulation, pixels
    min_angle_deg: float  # triangulation angle lower bound

    def __post_init__(self) -> None:
        require_min("init.sfm", self, "max_features", 1)
        require_min("init.sfm", self, "ratio epipolar_px reproj_px", strict=True)
        require_in("init.sfm", self, "ratio", 0, 1)
        require_in("init.sfm", self, "min_angle_deg", 0, 180)


@dataclass
class MASt3RConfig(FromConf):
    """MASt3R ONNX backend (contract in docs/init.md)."""

    SECTION = "init.mast3r"

    model: str | None  # path of the ONNX file (or --model)
    long_side: int  # network input long side, pixels (dynamic-shape models)
    min_conf: float  # MASt3R confidence (>= 1) below this -> invalid
    fit_shift: bool  # fit depth = s * pred + t instead of s * pred
    match_subsample: int  # pixel stride for the 3D reciprocal nearest-neighbour matches
    epipolar_px: float  # match check against the known epipolar geometry, scene pixels
    consistency_px: float  # geometric consistency of the aligned depth maps, pixels
    consistency_rel_depth: float  # ... and relative depth
    ransac_iters: int
    inlier_rel: float  # RANSAC inlier bound on relative depth error

    def __post_init__(self) -> None:
        require_min("init.mast3r", self, "long_side match_subsample ransac_iters", 1)
        require_min("init.mast3r", self, "epipolar_px consistency_px consistency_rel_depth inlier_rel", strict=True)
        require_min("init.mast3r", self, "min_conf")


@dataclass
class InitConfig(FromConf):
    """The init stage (values: conf/init/*.yaml, the default preset conf/init/mvs.yaml; nested
    sections likewise)."""

    SECTION = "init"

    backend: str  # one of BACKENDS
    seed: int
    voxel_norm: float  # cloud voxel size, unit-sphere radii (x scale_mat radius = mm)
    normal_knn: int
    random_points: int  # random backend: points in the unit sphere
    mvs: MVSConfig
    consistency: ConsistencyConfig
    sfm: SfMConfig
    mast3r: MASt3RConfig

    BACKENDS = ("mvs", "sfm", "mast3r", "random")  # pipeline.init.backends.BACKEND_MODULES implements each

    def __post_init__(self) -> None:
        nested_sections(self, "init", mvs=MVSConfig, consistency=ConsistencyConfig, sfm=SfMConfig, mast3r=MASt3RConfig)
        if self.backend not in self.BACKENDS:
            raise ConfigError(f"init.backend must be one of {', '.join(self.BACKENDS)}, got {self.backend!r}")
        require_min("init", self, "seed voxel_norm")  # voxel_norm 0: no voxel averaging
        require_min("init", self, "normal_knn", 3)  # a plane fit needs 3 points
        require_min("init", self, "random_points", 1)
