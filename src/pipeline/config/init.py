"""The init stage (conf/init)."""
from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.config.params import nested_sections
from pipeline.errors import ConfigError


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
    fill_width: int = 400  # width (px) of the absolute-difference sweep where NCC has no match (0: off)
    fill_window: int = 7  # its window side, coarse pixels (odd)
    fill_max_rms: float = 0.05  # its winner's RMS grey difference (object-mean units) above this -> invalid
    fill_min_std: float = 0.002  # its window's grey std (object-mean units) below this -> one grey, invalid
    # A hypothesis scores max(mean NCC over the sources, best source's NCC - this): a point
    # beside an occluding edge is hidden from some sources (>= 2: the mean alone).
    best_source_margin: float = 0.1
    # Holes of the consistent depth that good depth encloses, up to this fraction of the image's
    # pixels, are filled by harmonic interpolation and their points join the cloud (not the depth
    # maps, which stay two-view-confirmed); 0: off. pipeline.init.hole_fill.
    hole_fill_area: float = 0.00625
    hole_fill_max_bend: float = 0.02  # ... only where the points around it lie within this x its extent of a plane

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

    BACKENDS = ("mvs", "sfm", "mast3r", "random")  # pipeline.init.backends.BACKEND_MODULES implements each

    def __post_init__(self) -> None:
        nested_sections(self, "init", mvs=MVSConfig, consistency=ConsistencyConfig, sfm=SfMConfig, mast3r=MASt3RConfig)
        if self.backend not in self.BACKENDS:
            raise ConfigError(f"init.backend must be one of {', '.join(self.BACKENDS)}, got {self.backend!r}")
        if self.voxel_norm < 0:
            raise ConfigError(f"init.voxel_norm must be >= 0, got {self.voxel_norm}")
