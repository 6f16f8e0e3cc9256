"""The surfel model: the parameters of 2D Gaussian surfels and their PLY files, below the
trainer (:mod:`pipeline.optimize` trains them; meshing, evaluation and the reports read them).

Frame and units: training runs in the scene's **normalised frame** (the unit sphere of
``scale_mat``: ``x_world_mm = norm_to_world @ x_norm``), so learning rates, thresholds and
sizes mean the same on a 5 mm and a 500 mm object. Files are written in the **world frame,
mm** (centres and scales multiplied by the scale_mat radius), so that a surfel PLY overlays
the mesh and the ground truth.

Parameters (as 2DGS): ``means (P,3)``, ``log_scales (P,2)``, ``quats (P,4)`` (wxyz, not
necessarily unit), ``opacity_logits (P,)``, ``sh_dc (P,1,3)``, ``sh_rest (P,K-1,3)``.

* :mod:`params`: :class:`SurfelParams`, the parameter container.
* :mod:`io`: the 2DGS-layout PLY (read and write) and the 3DGS export for viewers.
"""
from __future__ import annotations

from pipeline.surfels.io import (
    THICKNESS_RATIO,
    ply_attribute_names,
    read_surfel_ply,
    splats_3dgs_attribute_names,
    write_splats_3dgs_ply,
    write_surfel_ply,
)
from pipeline.surfels.params import PARAM_NAMES, SurfelInitError, SurfelParams

__all__ = ["PARAM_NAMES", "THICKNESS_RATIO", "SurfelInitError", "SurfelParams", "ply_attribute_names",
           "read_surfel_ply", "splats_3dgs_attribute_names", "write_splats_3dgs_ply", "write_surfel_ply"]
