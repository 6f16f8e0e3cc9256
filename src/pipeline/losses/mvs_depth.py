"""The MVS depth term L_mvs: the rendered depth against the init's MVS depth maps. Torch,
differentiable, any float dtype; depth maps ``(H, W)`` camera-frame z, 0 where there is none.
"""
from __future__ import annotations

import torch

def mvs_depth_loss(depth: torch.Tensor, mvs_depth: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean ``|depth - mvs_depth| / mvs_depth`` over ``valid`` pixels (all ``(H, W)``; 0 when
    none is valid): relative, so it means the same at every resolution and scale."""
    if not bool(valid.any()):
        return depth.sum() * 0.0
    d, m = depth[valid], mvs_depth[valid].to(depth)
    return ((d - m).abs() / m).mean()
