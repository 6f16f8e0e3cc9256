"""The mask term: the rendered alpha against the object mask. Torch, differentiable, any
float dtype.
"""
from __future__ import annotations

import torch

def mask_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean ``|alpha - mask|``: background pixels pull alpha to 0, object pixels to 1."""
    return (alpha - mask.to(alpha)).abs().mean()
