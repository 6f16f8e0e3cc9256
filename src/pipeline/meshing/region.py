"""The object's region for depth fused without masks (docs/inputs.md, "Without masks").

Masks keep the background and the table out of the mesh; without them the region of
:func:`pipeline.labelling.label_scene` does: the sphere that holds the object (the unit
sphere, grown where the object reaches beyond it), the half-space above the support the
object stands on (by the band its own residuals measure), and the object's footprint on the
support. ``gcgs masks`` derives its masks from the same labelling, so mask and mesh agree
about where the object ends.

Frame and units: world frame, mm (lengths of a capture without a unit are in its units).
"""
from __future__ import annotations

import numpy as np

from pipeline import geometry
from pipeline.config.mesh import MeshConfig
from pipeline.labelling import Region, label_scene


def crop_depths(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, region: Region) -> np.ndarray:
    """The depth maps with 0 (no depth) wherever the pixel's point is outside ``region``."""
    out = np.array(depths_mm, np.float64, copy=True)
    for d, Ki, T in zip(out, K, world_to_cam):
        has = d > 0
        d[has & ~region.contains(geometry.backproject_depth(Ki, T, d))] = 0.0
    return out


def crop_mesh_vertices(vertices_mm: np.ndarray, triangles: np.ndarray, region: Region) -> np.ndarray:
    """The triangles with every vertex inside ``region``."""
    inside = region.contains(vertices_mm)
    return triangles[inside[triangles].all(axis=1)]


def cut_to_region(depths_mm: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, norm_to_world: np.ndarray,
                  cfg: MeshConfig, masked: bool) -> tuple[np.ndarray, Region | None, dict]:
    """``cfg.region`` applied to depth maps about to be fused: with ``auto``, only when no
    mask has cut them (``masked`` False). Returns the depth maps (cut or as given), the
    region (``None`` when not applied) and facts for the stage's JSON."""
    if cfg.region == "off" or (cfg.region == "auto" and masked):
        return depths_mm, None, {"region": None}
    scale = float(norm_to_world[0, 0])
    voxel_mm, _ = cfg.sizes_mm(scale)
    labels = label_scene(depths_mm, K, world_to_cam, norm_to_world, voxel_mm, cfg.region_plane_margin_norm * scale)
    cut = crop_depths(depths_mm, K, world_to_cam, labels.region)
    facts = {"region": {**labels.region.facts(), **labels.facts,
                        "depth_pixels_cut": int((depths_mm > 0).sum() - (cut > 0).sum())}}
    return cut, labels.region, facts
