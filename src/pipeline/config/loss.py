"""The loss weights (conf/loss)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from pipeline.errors import ConfigError


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
    # Of each reference pixel's valid L_mv pairs only this many of lowest NCC cost count (a
    # source that does not see the point matches worst); 0: every source (PGSR's).
    mv_best_sources: int = 0
    mv_max_cost: float = 2.0  # L_mv pairs whose cost 1 - NCC exceeds this are dropped (2: none)
    # Adaptive support weights of L_mv's and the photo reset's NCC: patch pixels weighted by
    # exp(-|grey - centre grey| / mv_ncc_gamma) (grey in [0, 1]). 0: plain NCC (PGSR).
    mv_ncc_gamma: float = 0.0
    # L_mv's reference pixels: only where the rendered normal is within this angle of the ray
    # to the camera (90: every surface pixel, PGSR's).
    mv_max_incidence_deg: float = 70.0
    # L_smooth: edge-aware smoothness of the rendered normals (neighbouring surface pixels'
    # unit normals alike where the image is flat: weight exp(-smooth_gamma |grad I|)), from
    # start.mv. 0: off.
    lambda_smooth: float = 0.0
    smooth_gamma: float = 10.0
    # L_smooth only between pixels whose 5x5 grey std (training resolution) is below this,
    # where the image gives L_photo and L_mv nothing to go by. 0: every surface pixel.
    smooth_max_std: float = 0.0

    def __post_init__(self) -> None:
        if self.mv_patch < 3 or self.mv_patch % 2 == 0:
            raise ConfigError(f"loss.mv_patch must be odd and >= 3, got {self.mv_patch}")
        if not all(math.isfinite(x) and x >= 0 for x in (self.lambda_smooth, self.smooth_gamma, self.smooth_max_std)):
            raise ConfigError("loss.lambda_smooth, smooth_gamma and smooth_max_std must be finite and >= 0")
        if not (math.isfinite(self.mv_ncc_gamma) and self.mv_ncc_gamma >= 0):
            raise ConfigError(f"loss.mv_ncc_gamma must be a finite number >= 0 (0: plain NCC), got {self.mv_ncc_gamma}")
        if min(self.lambda_mv, self.lambda_mvgeo, self.mv_min_patch_std) < 0 or self.mv_max_fb_px <= 0:
            raise ConfigError("loss.lambda_mv, lambda_mvgeo and mv_min_patch_std must be >= 0 and mv_max_fb_px > 0")
        if not (isinstance(self.mv_best_sources, int) and self.mv_best_sources >= 0):
            raise ConfigError(f"loss.mv_best_sources must be an int >= 0 (0: every source), got {self.mv_best_sources!r}")
        if not 0.0 < self.mv_max_cost <= 2.0:
            raise ConfigError(f"loss.mv_max_cost must be in (0, 2] (1 - NCC lies in [0, 2]), got {self.mv_max_cost}")
        if not 0.0 < self.mv_max_incidence_deg <= 90.0:
            raise ConfigError(f"loss.mv_max_incidence_deg must be in (0, 90], got {self.mv_max_incidence_deg}")
        if self.lambda_mvs < 0 or not 0.0 <= self.mvs_final:
            raise ConfigError(f"loss.lambda_mvs and loss.mvs_final must be >= 0, got {self.lambda_mvs}, {self.mvs_final}")
        if not 0.0 < self.gcf_max_dissimilarity <= 2.0:
            raise ConfigError(f"loss.gcf_max_dissimilarity must be in (0, 2] (1 - cos lies in [0, 2]), "
                              f"got {self.gcf_max_dissimilarity}")
