"""The loss weights (conf/loss)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from pipeline.config.params import FromConf, require_in, require_min
from pipeline.errors import ConfigError


@dataclass
class LossConfig(FromConf):
    """Loss weights (values, with the GCGS paper's where they differ: conf/loss/gcgs.yaml)."""

    SECTION = "loss"

    lambda_dssim: float  # L_photo = (1 - lambda_dssim) L1 + lambda_dssim D-SSIM
    lambda_gcf: float  # L_gcf, the multi-view feature term (GCGS)
    lambda_nor: float  # L_nor = lambda_nc L_nc + lambda_ngc L_ngc, the normal prior (GCGS)
    lambda_nc: float
    lambda_ngc: float
    lambda_d: float  # 2DGS depth distortion
    lambda_dn: float  # 2DGS depth-normal consistency
    lambda_mask: float  # |alpha - mask|, only where masks are used
    gcf_max_dissimilarity: float  # L_gcf pairs with 1 - cos at or above this are outliers (FatesGS); 2: none
    # L_mvs: relative L1 of the rendered median depth to the init's MVS depth where it has one
    # (init/NAME/depth/*.npz; 0: off), its weight going linearly to mvs_final x lambda_mvs.
    lambda_mvs: float
    mvs_final: float
    # L_mv (PGSR): 1 - NCC of grey patches warped by the homography of each pixel's rendered
    # plane into the other input views, at the scene's full resolution, weighted by the
    # forward-backward reprojection (pipeline.losses.multiview); lambda_mvgeo weights that reprojection
    # error itself. 0: off.
    lambda_mv: float
    lambda_mvgeo: float
    mv_patch: int  # NCC patch side, full-resolution pixels (odd)
    mv_min_patch_std: float  # grey std below which a patch is flat: no NCC there
    mv_max_fb_px: float  # forward-backward reprojection error (training pixels) above which a pair is occluded
    # Of each reference pixel's valid L_mv pairs only this many of lowest NCC cost count (a
    # source that does not see the point matches worst); 0: every source (PGSR's).
    mv_best_sources: int
    mv_max_cost: float  # L_mv pairs whose cost 1 - NCC exceeds this are dropped (2: none)
    # Adaptive support weights of L_mv's and the photo reset's NCC: patch pixels weighted by
    # exp(-|grey - centre grey| / mv_ncc_gamma) (grey in [0, 1]). 0: plain NCC (PGSR).
    mv_ncc_gamma: float
    # L_mv's reference pixels: only where the rendered normal is within this angle of the ray
    # to the camera (90: every surface pixel, PGSR's).
    mv_max_incidence_deg: float
    # L_smooth: edge-aware smoothness of the rendered normals (neighbouring surface pixels'
    # unit normals alike where the image is flat: weight exp(-smooth_gamma |grad I|)), from
    # start.mv. 0: off.
    lambda_smooth: float
    smooth_gamma: float
    # L_smooth only between pixels whose 5x5 grey std (training resolution) is below this,
    # where the image gives L_photo and L_mv nothing to go by. 0: every surface pixel.
    smooth_max_std: float

    def __post_init__(self) -> None:
        # A negative weight would maximise its term; L_photo mixes L1 and D-SSIM by lambda_dssim.
        require_in("loss", self, "lambda_dssim", 0, 1)
        require_min("loss", self, "lambda_gcf lambda_nor lambda_nc lambda_ngc lambda_d lambda_dn lambda_mask")
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
