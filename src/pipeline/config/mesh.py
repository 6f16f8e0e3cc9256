"""TSDF meshing (conf/mesh)."""
from __future__ import annotations

from dataclasses import dataclass

from pipeline.config.params import FromConf
from pipeline.errors import ConfigError


@dataclass
class MeshConfig(FromConf):
    """TSDF meshing of depth maps (values: conf/mesh/default.yaml; ``gcgs mesh``, ``gcgs tsdf``).

    Sizes are in unit-sphere radii (x the scale_mat radius = mm). Cleaning keeps every
    connected component with at least ``min_component_fraction`` of the largest one's
    triangles, so an object in several separate parts keeps its parts while small floaters go."""

    SECTION = "mesh"

    voxel_norm: float
    trunc_norm: float
    min_component_fraction: float
    # gcgs mesh (surfels -> depth -> TSDF):
    depth: str  # rendered depth fused: median (2DGS on DTU) | expected
    alpha_min: float  # pixels with less accumulated alpha have no depth
    masks: bool  # zero the depth outside the input views' masks (where the scene has masks)
    virtual_per_pair: int  # virtual views rendered between each pair of input views
    # Where the init's MVS depth map (two-view confirmed) agrees with the rendered depth to
    # this relative tolerance, that pixel fuses the init's depth instead; 0: off.
    init_depth_rel_tol: float
    # Bounding region for depth fused without masks (meshing/region.py): the unit sphere and,
    # when the depth shows one, the half-space above the support plane (the table).
    region: str  # auto (when no mask cuts the fused depth) | on | off
    region_plane_share: float  # a plane is the table when at least this share of depth points lie on it
    region_plane_margin_norm: float  # the region starts this far above the table (unit-sphere radii)
    # Holes whose boundary fits in a sphere of this radius (unit-sphere radii) are closed where
    # the fused depth maps support the new triangles (meshing/holes.py); 0: off.
    fill_holes_norm: float

    def __post_init__(self) -> None:
        if self.region not in ("auto", "on", "off"):
            raise ConfigError(f"mesh.region must be auto, on or off, got {self.region!r}")
        if not 0 < self.region_plane_share <= 1 or self.region_plane_margin_norm < 0:
            raise ConfigError("mesh: region_plane_share must be in (0, 1] and region_plane_margin_norm >= 0")
        if self.depth not in ("median", "expected"):
            raise ConfigError(f"mesh.depth must be median or expected, got {self.depth!r}")
        if not 0 <= self.init_depth_rel_tol < 1:
            raise ConfigError(f"mesh.init_depth_rel_tol must be in [0, 1), got {self.init_depth_rel_tol}")
        if not 0 <= self.alpha_min < 1 or self.virtual_per_pair < 0:
            raise ConfigError("mesh: alpha_min must be in [0, 1) and virtual_per_pair >= 0")
        if not 0 < self.voxel_norm < self.trunc_norm:
            raise ConfigError(f"mesh: need 0 < voxel_norm < trunc_norm, got {self.voxel_norm}, {self.trunc_norm}")
        if not 0 <= self.fill_holes_norm < float("inf"):
            raise ConfigError(f"mesh.fill_holes_norm must be finite and >= 0, got {self.fill_holes_norm}")
        if not 0 <= self.min_component_fraction <= 1:
            raise ConfigError(f"mesh.min_component_fraction must be in [0, 1], got {self.min_component_fraction}")

    def sizes_mm(self, norm_scale_mm: float) -> tuple[float, float]:
        """``(voxel_mm, trunc_mm)`` for a scene whose unit sphere has radius ``norm_scale_mm``."""
        return self.voxel_norm * norm_scale_mm, self.trunc_norm * norm_scale_mm
