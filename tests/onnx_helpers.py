"""Tiny torch modules with the DSINE / Vis-MVSNet contracts, exported to real ONNX files.

Used by tests/test_onnx_models.py and tests/test_priors_stage.py; they run through a
real onnxruntime session, not a mock.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import torch
import torch.nn.functional as F

# Analytic sphere seen by the fake DSINE model: centre (camera frame) and radius, in the
# same units as the test scene (mm).
SPHERE_CENTRE_CAM = (10.0, -5.0, 600.0)
SPHERE_RADIUS = 80.0


class FakeDSINE(torch.nn.Module):
    """Emits the analytic normal of a sphere in DSINE's convention.

    For each pixel (integer centres, ray ``K^-1 (x, y, 1)`` from the ``intrinsics`` input
    -- so wrong padding or intrinsics shift the result), intersect the ray with the
    sphere; the outward sphere normal at the visible hit faces the camera, and DSINE
    reports normals pointing *away* from the camera (``n . ray > 0``, see docs/priors.md),
    so the module emits its negation. Missed pixels get the ray direction itself.
    The image only contributes a zero term so that the input is used.
    """

    def forward(self, image: torch.Tensor, intrinsics: torch.Tensor) -> torch.Tensor:
        _, _, H, W = image.shape
        K = intrinsics[0]
        ys = torch.arange(H, dtype=torch.float32).view(H, 1).expand(H, W)
        xs = torch.arange(W, dtype=torch.float32).view(1, W).expand(H, W)
        rx = (xs - K[0, 2] - K[0, 1] * (ys - K[1, 2]) / K[1, 1]) / K[0, 0]
        ry = (ys - K[1, 2]) / K[1, 1]
        ray = F.normalize(torch.stack([rx, ry, torch.ones_like(rx)], 0), dim=0)  # (3,H,W)
        c = torch.tensor(SPHERE_CENTRE_CAM).view(3, 1, 1)
        b = (ray * c).sum(0)
        disc = b * b - (c * c).sum() + SPHERE_RADIUS**2
        hit = disc > 0
        t = b - torch.sqrt(torch.clamp(disc, min=0.0))
        outward = (ray * t - c) / SPHERE_RADIUS
        normal = torch.where(hit.unsqueeze(0), -outward, ray)
        return (normal + 0.0 * image[0]).unsqueeze(0)


class FakeVisMVSNet(torch.nn.Module):
    """32 channels at 1/2 resolution: a fixed random conv on the input, stride 2."""

    def __init__(self, channels: int = 32) -> None:
        super().__init__()
        g = torch.Generator().manual_seed(0)
        self.weight = torch.nn.Parameter(torch.randn(channels, 3, 3, 3, generator=g), requires_grad=False)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return F.conv2d(image, self.weight, stride=2, padding=1)


class WrongNames(torch.nn.Module):
    def forward(self, img: torch.Tensor) -> torch.Tensor:
        return img[:, :, ::2, ::2]


class NaNFeatures(torch.nn.Module):
    def forward(self, image: torch.Tensor) -> torch.Tensor:
        f = F.avg_pool2d(image, 2).repeat(1, 11, 1, 1)[:, :32]
        return f / 0.0 * 0.0  # 0/0: NaN everywhere


def export(module: torch.nn.Module, args: tuple, path: Path, inputs: list[str], outputs: list[str],
           dynamic: dict | None = None) -> Path:
    """Export with the TorchScript exporter (the dynamo exporter needs onnxscript)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module.eval(), args, str(path), input_names=inputs, output_names=outputs,
                          dynamic_axes=dynamic, dynamo=False, opset_version=17)
    return path


def export_fake_dsine(path: Path) -> Path:
    dyn = {"image": {2: "H", 3: "W"}, "normal": {2: "H", 3: "W"}}
    return export(FakeDSINE(), (torch.zeros(1, 3, 64, 96), torch.eye(3).unsqueeze(0) * 100),
                  path, ["image", "intrinsics"], ["normal"], dyn)


def export_fake_vismvsnet(path: Path, module: torch.nn.Module | None = None) -> Path:
    dyn = {"image": {2: "H", 3: "W"}, "features": {2: "h", 3: "w"}}
    return export(module or FakeVisMVSNet(), (torch.zeros(1, 3, 64, 96),), path, ["image"], ["features"], dyn)
