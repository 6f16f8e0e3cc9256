"""The ``random`` backend (ablation): points uniform in the scene's unit sphere."""
from __future__ import annotations

import numpy as np

from pipeline.config.init import InitConfig
from pipeline.data.scene import Scene
from pipeline.init.io import InitResult, PointCloud


def run(scene: Scene, cfg: InitConfig) -> InitResult:
    """``cfg.random_points`` points uniform in the unit sphere (world mm), grey, random
    unit normals, confidence 0 (nothing was observed)."""
    rng = np.random.default_rng(cfg.seed)
    n = int(cfg.random_points)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.random(n) ** (1.0 / 3.0)  # uniform in volume
    p_norm = d * r[:, None]
    p_world = p_norm @ scene.norm_to_world[:3, :3].T + scene.norm_to_world[:3, 3]
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cloud = PointCloud(p_world, np.full((n, 3), 0.5, np.float32), normals.astype(np.float32), np.zeros(n, np.float32))
    return InitResult(cloud, None, {})
