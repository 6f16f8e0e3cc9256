"""The loss terms of the optimisation, one module per term (docs/optimize.md). Differentiable
torch functions, in the lowest layer: they import torch and numpy only.

* :mod:`photometric`: L1 + D-SSIM against the input image.
* :mod:`feature`: GCGS's geometric-consistent feature loss L_gcf (Eq. 4-9).
* :mod:`normal`: GCGS's normal-prior consistency L_nor (Eq. 10-12); 2DGS depth-normal consistency.
* :mod:`multiview`: PGSR's multi-view photometric and geometric consistency L_mv.
* :mod:`smoothness`: edge-aware normal smoothness L_smooth.
* :mod:`mvs_depth`: the MVS depth term L_mvs.
* :mod:`mask`: the mask term.

2DGS's depth distortion is the renderer's ``distortion`` map, averaged in the training loop
(:mod:`pipeline.optimize.train`).
"""
from __future__ import annotations

from pipeline.losses.feature import cosine, gcf_loss, sample_features
from pipeline.losses.mask import mask_loss
from pipeline.losses.multiview import (
    SourceView,
    best_source_ncc,
    multiview_consistency,
    plane_homographies,
    reference_pixels,
    textured_pixels,
)
from pipeline.losses.mvs_depth import mvs_depth_loss
from pipeline.losses.normal import depth_normal_loss, depth_to_normals, normal_consistency_losses, sobel
from pipeline.losses.photometric import photometric_loss, ssim
from pipeline.losses.smoothness import flat_pixels, normal_smoothness_loss

__all__ = [
    "SourceView",
    "best_source_ncc",
    "cosine",
    "depth_normal_loss",
    "depth_to_normals",
    "flat_pixels",
    "gcf_loss",
    "mask_loss",
    "multiview_consistency",
    "mvs_depth_loss",
    "normal_consistency_losses",
    "normal_smoothness_loss",
    "photometric_loss",
    "plane_homographies",
    "reference_pixels",
    "sample_features",
    "sobel",
    "ssim",
    "textured_pixels",
]
