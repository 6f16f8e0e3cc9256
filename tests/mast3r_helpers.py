"""Tiny torch modules with the MASt3R contract, exported to real ONNX files.

:class:`FakeMASt3R` knows the exact geometry of the test scene (tests/init_scene.py):
it recognises which stored view each input image is (nearest stored image, L1) and
returns the true pointmaps of the pair in camera 1's frame, multiplied by a per-pair
scale that is *not* metric (as MASt3R's are). The backend must undo that scale from
the known cameras alone.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from init_scene import ray_cast, spheres_world
from pipeline import geometry
from pipeline.data.scene import Scene
from pipeline.init.mast3r import preprocess


def pair_scale(i: int, j: int) -> float:
    """The non-metric scale of the fake model's output for the pair (i, j)."""
    return 1e-3 * (1.0 + 0.3 * i + 0.1 * j)


def true_pointmaps(scene: Scene, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``P[i, j]``: view j's pixels (at ``size``) in camera i's frame (mm); ``C[j]``: confidence 5 on the spheres, 1 on the background
    (placed on a far plane so that it has a finite point)."""
    w, h = size
    N = scene.num_views
    world = []
    conf = []
    for v in range(N):
        K = geometry.scale_intrinsics(scene.K[v], w / scene.width, h / scene.height)
        z, X = ray_cast(K, scene.world_to_cam[v], h, w, spheres_world(scene))
        hit = z > 0
        far = geometry.backproject_depth(K, scene.world_to_cam[v], np.full((h, w), 2000.0))
        world.append(np.where(hit[..., None], X, far))
        conf.append(np.where(hit, 5.0, 1.0))
    P = np.zeros((N, N, h, w, 3), np.float32)
    for i in range(N):
        T = scene.world_to_cam[i]
        for j in range(N):
            P[i, j] = world[j] @ T[:3, :3].T + T[:3, 3]
    return P, np.stack(conf).astype(np.float32)


class FakeMASt3R(torch.nn.Module):
    def __init__(self, scene: Scene, size: tuple[int, int]) -> None:
        super().__init__()
        P, C = true_pointmaps(scene, size)
        imgs = np.concatenate([preprocess(img, size) for img in scene.images])
        self.register_buffer("imgs", torch.from_numpy(imgs))
        self.register_buffer("P", torch.from_numpy(P))
        self.register_buffer("C", torch.from_numpy(C))
        n = scene.num_views
        S = np.array([[pair_scale(i, j) for j in range(n)] for i in range(n)], np.float32)
        self.register_buffer("S", torch.from_numpy(S).view(n * n))

    def which(self, img: torch.Tensor) -> torch.Tensor:
        return (self.imgs - img).abs().mean(dim=(1, 2, 3)).argmin()

    def forward(self, img1: torch.Tensor, img2: torch.Tensor):
        i, j = self.which(img1), self.which(img2)
        Pi = torch.index_select(self.P, 0, i.view(1))[0]
        p1 = torch.index_select(Pi, 0, i.view(1))
        p2 = torch.index_select(Pi, 0, j.view(1))
        c1 = torch.index_select(self.C, 0, i.view(1))
        c2 = torch.index_select(self.C, 0, j.view(1))
        scale = torch.index_select(self.S, 0, (i * self.C.shape[0] + j).view(1))
        return p1 * scale, c1, p2 * scale, c2


class PassThrough(torch.nn.Module):
    """Tensors of the contract's shapes (the images as points); the names are given at
    export, so the tests can export it with the right names or a wrong one."""

    def forward(self, img1: torch.Tensor, img2: torch.Tensor):
        pts = img1.permute(0, 2, 3, 1)
        conf = img1[:, 0] + 1.0
        return pts, conf, img2.permute(0, 2, 3, 1), conf


class WrongRank(torch.nn.Module):
    """Confidence with a channel axis (rank 4) instead of (1, H, W)."""

    def forward(self, img1: torch.Tensor, img2: torch.Tensor):
        return img1.permute(0, 2, 3, 1), img1[:, :1], img2.permute(0, 2, 3, 1), img2[:, 0]


def export(module: torch.nn.Module, size: tuple[int, int], path: Path,
           outputs=("pts3d_1", "conf_1", "pts3d_2", "conf_2")) -> Path:
    w, h = size
    x = torch.zeros(1, 3, h, w)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(module.eval(), (x, x), str(path), input_names=["img1", "img2"], output_names=list(outputs),
                          dynamo=False, opset_version=17)
    return path
