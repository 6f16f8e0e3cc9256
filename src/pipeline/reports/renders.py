"""A small picture of one scene's result for the report (``reports/renders/SCENE.png``): at
the first input view, side by side, the input image, the trained surfels' rendered colour,
their rendered normals, and the extracted mesh shaded by a headlight.

Normals are shown in the camera frame with OpenGL-style axes (x right, y up, z towards the
viewer) mapped to RGB as ``(n + 1) / 2``: a surface facing the camera is light blue.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from pipeline import atomic
from pipeline.data import dtu
from pipeline.evaluation.gt import read_mesh
from pipeline.meshing.raycast import MeshCaster
from pipeline.optimize.surfels import read_surfel_ply
from pipeline.rasterizer import Camera, rasterize

PANEL_WIDTH = 160  # px; four panels of 160 x 120 keep a PNG under 200 KB (scan24: ~150 KB)
LABELS = ("input view {view}", "surfels: colour", "surfels: normal", "mesh")
OPENCV_TO_OPENGL = np.array([1.0, -1.0, -1.0])


def normal_rgb(normal_cam: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` in [0, 1] of OpenCV camera-frame unit normals; black where not ``valid``."""
    return np.where(valid[..., None], np.clip((normal_cam * OPENCV_TO_OPENGL + 1) / 2, 0, 1), 0.0)


def headlight(normal_cam: np.ndarray, hit: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Grey ``(H, W, 3)`` Lambert shading with the light at the camera; black on misses."""
    h, w = hit.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    rays = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    shade = 0.15 + 0.85 * np.clip(-np.sum(normal_cam * rays, -1), 0, 1)
    return np.repeat(np.where(hit, shade, 0.0)[..., None], 3, -1)


@torch.no_grad()
def scene_panels(scene_dir: str | Path, surfels_ply: str | Path, mesh_ply: str | Path,
                 panel_width: int = PANEL_WIDTH, background: float = 0.0, backend: str = "cpu") -> np.ndarray:
    """``(H, 4 W, 3)`` uint8 RGB: input image, surfel colour, surfel normal, mesh, at the
    prepared scene's first view, each ``panel_width`` px wide (the scene's aspect ratio)."""
    width, height = dtu.stored_image_size(scene_dir)
    size = (panel_width, max(1, round(panel_width * height / width)))
    scene = dtu.load_scene(scene_dir, view_ids=None, resolution=size)
    K = scene.K[0]
    params = read_surfel_ply(surfels_ply, scene.norm_to_world)
    out = rasterize(params.surfels(params.sh_degree_max),
                    Camera(K, scene.world_to_cam_normalised()[0], size[0], size[1]), backend)
    alpha = out.alpha.double().numpy()
    colour = np.clip(out.features.double().numpy() + background * (1 - alpha[..., None]), 0, 1)
    normal = normal_rgb(out.normal_cam.double().numpy(), alpha > 0.5)
    hits = MeshCaster(*read_mesh(mesh_ply)).cast(K, scene.world_to_cam[0], size[1], size[0])
    mesh = headlight(hits.normal_cam, hits.depth_mm > 0, K)
    panels = []
    for image, label in zip((scene.images[0], colour, normal, mesh), LABELS):
        panel = (np.clip(image, 0, 1) * 255).round().astype(np.uint8).copy()
        cv2.putText(panel, label.format(view=scene.view_ids[0]), (4, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    (255, 255, 0), 1, cv2.LINE_AA)
        panels.append(panel)
    return np.concatenate(panels, axis=1)


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError(f"{path}: PNG encoding failed")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic.write_bytes(path, data.tobytes())
