"""Opacity reset by multi-view photo-consistency: the surfels that are the visible surface
where the rendered plane matches no other input view (docs/optimize.md "Resetting where the
views disagree").

Why: where the init or densification put a surface in front of the true one (an occluder's
edge spilled over the surface behind it), every view renders the same wrong depth, so the
geometric terms agree with it and L_mv's gradient, local in depth, cannot move it tens of
millimetres. Its patch does not match the other views, though. Making it transparent lets
the surface behind show and be fitted; where nothing is behind, the photometric loss
raises its opacity again (pruning it instead left holes: measured in the docs).

Frames: the normalised frame of training; pixels with integer centres."""
from __future__ import annotations

import torch


@torch.no_grad()
def visible_surfels_at(means: torch.Tensor, K: torch.Tensor, world_to_cam: torch.Tensor, depth: torch.Tensor,
                       marked: torch.Tensor, depth_rel_tol: float) -> torch.Tensor:
    """``(P,)`` bool: surfels whose centre projects (rounded to the nearest pixel) into a
    ``marked`` pixel of the ``(h, w)`` map and lies within ``depth_rel_tol`` (relative) of
    the rendered ``depth`` there (0 = none), i.e. the surfel is at that pixel's surface.

    ``means (P, 3)`` in the frame ``world_to_cam (4, 4)`` maps to the camera; ``K`` the
    intrinsics of the map."""
    h, w = depth.shape
    Xc = means.to(torch.float64) @ world_to_cam[:3, :3].to(torch.float64).t() + world_to_cam[:3, 3].to(torch.float64)
    z = Xc[:, 2]
    in_front = z > 1e-9
    uvw = Xc @ K.to(torch.float64).t()
    zs = torch.where(in_front, z, torch.ones_like(z))
    u = torch.round(uvw[:, 0] / zs)
    v = torch.round(uvw[:, 1] / zs)
    inside = in_front & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    ui = torch.where(inside, u, torch.zeros_like(u)).long()
    vi = torch.where(inside, v, torch.zeros_like(v)).long()
    d = depth.to(torch.float64)[vi, ui]
    return inside & marked[vi, ui] & (d > 0) & ((z - d).abs() <= depth_rel_tol * d)
