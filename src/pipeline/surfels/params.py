"""The trainable surfel parameters (normalised frame; see :mod:`pipeline.surfels`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from pipeline.errors import InputError
from pipeline.rasterizer import Surfels

PARAM_NAMES = ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")


class SurfelInitError(InputError):
    """The init cloud cannot seed surfels (names the file and the problem)."""


@dataclass
class SurfelParams:
    """The optimised tensors (normalised frame), each ``requires_grad`` leaf."""

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor

    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree_max(self) -> int:
        return int(round(math.sqrt(self.sh_rest.shape[1] + 1))) - 1

    def tensors(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k) for k in PARAM_NAMES}

    def replace(self, new: dict[str, torch.Tensor]) -> None:
        for k, v in new.items():
            setattr(self, k, v)

    def surfels(self, sh_degree: int, min_scale: float = 0.0) -> Surfels:
        """Activated surfels for the rasterizer (normalised frame)."""
        features = torch.cat([self.sh_dc, self.sh_rest], dim=1)
        scales = torch.exp(self.log_scales)
        if min_scale > 0:
            scales = scales.clamp_min(min_scale)
        return Surfels(self.means, self.quats, scales, torch.sigmoid(self.opacity_logits), features, sh_degree=sh_degree)
