"""Synthetic scenes with exact ground truth, ray cast (Open3D) with real DTU cameras.

Frames: objects are modelled in a local frame (mm, z up, origin on the ground) and placed
in the DTU world frame (mm) of the camera source by :func:`table_frame`.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from pipeline import geometry
from pipeline.atomic import atomic_dir
from pipeline.data import dtu
from pipeline.synth import shapes
from pipeline.synth.render import Renderer, snap

GROUND_BELOW_AIM_MM = 60.0  # the table lies this far below the point the cameras aim at
GT_GROUND_MARGIN_MM = 40.0  # GT keeps the table within this distance of the object footprint
PLANE_ABOVE_GROUND_MM = 1.0  # completeness uses GT points above this (the object only)
MAX_ROLL_RATIO = 0.1  # see table_frame

# name -> (scan id, builder, what it stresses)
SCENES: dict[str, tuple[int, Callable[[int], list[shapes.Part]], str]] = {
    "synth_textureless": (1001, shapes.textureless_blob, "a large smooth region of one plain colour"),
    "synth_relief": (1002, shapes.relief_sphere, "fine high-frequency geometric detail (~1.5 mm bumps, 3-8 mm periods)"),
    "synth_thin": (1003, shapes.thin_structures, "thin fins (2-3.5 mm) and rods (4-6 mm) and sharp box edges"),
    "synth_dark_wide": (1004, shapes.relief_sphere, "a dark capture (mean 0.06 inside the masks) meant for "
                        "views 6, 24, 40, 38-41 degrees apart (DTU's inputs 23/24/33: 10-12)"),
}
# Scenes rendered as a dark capture: one gain for every view, chosen so that the mean RGB
# value inside the object masks over all views is this (then 8-bit quantised, like any
# PNG): real scans brought by users were this dark.
DARK_MASK_MEAN = {"synth_dark_wide": 0.06}
# Input views a scene is made for when they are not the DTU default (recorded in scene.json
# as ``suggested_views``; prepare it with these views).
SUGGESTED_VIEWS = {"synth_dark_wide": [6, 24, 40]}


@dataclass
class SynthScene:
    """An object on a ground plane in the DTU world frame (mm)."""

    name: str
    scan_id: int
    seed: int
    parts: list[shapes.Part]  # local frame
    local_to_world: np.ndarray  # 4x4 rigid
    light_dir_world: np.ndarray  # (3,) unit, towards the light

    @property
    def up_world(self) -> np.ndarray:
        return self.local_to_world[:3, 2]

    def to_world(self, points_local: np.ndarray) -> np.ndarray:
        # Summed in a fixed order, not by BLAS: the GT files get the same bytes on any CPU.
        R, t = self.local_to_world[:3, :3], self.local_to_world[:3, 3]
        p = np.asarray(points_local, np.float64)
        return p[:, 0:1] * R[:, 0] + p[:, 1:2] * R[:, 1] + p[:, 2:3] * R[:, 2] + t

    def to_local(self, points_world: np.ndarray) -> np.ndarray:
        return (points_world - self.local_to_world[:3, 3]) @ self.local_to_world[:3, :3]

    def ground_plane(self) -> np.ndarray:
        """``P`` (4,): ``[x, 1] @ P > 0`` for world points above the evaluation plane."""
        up = self.up_world
        origin = self.local_to_world[:3, 3] + PLANE_ABOVE_GROUND_MM * up
        # Summed in a fixed order, not by BLAS (whose dot product rounds differently on AVX-512).
        return np.r_[up, -(up[0] * origin[0] + up[1] * origin[1] + up[2] * origin[2])]

    def gt_mesh_local(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's parts plus a disk of table reaching ``GT_GROUND_MARGIN_MM`` beyond
        its footprint (local mm), hidden parts included (see :func:`visible_gt_mesh`)."""
        allv = np.concatenate([p.vertices for p in self.parts])
        radius = np.linalg.norm(allv[:, :2], axis=1).max() + GT_GROUND_MARGIN_MM
        return shapes.merge([(p.vertices, p.triangles) for p in self.parts] + [shapes.ground_disk(radius)])


def table_frame(cams: dtu.DTUCameras) -> np.ndarray:
    """Local (table) frame -> world, 4x4 rigid, from the cameras alone.

    * up: DTU's robot keeps the cameras level (scan24: every x axis within 5 degrees of
      horizontal), so up is the unit vector most orthogonal to all camera x axes (the
      least eigenvector of sum x x^T), signed so the cameras are above the table.
    * aim: the point nearest to all optical axes (least squares); the table lies
      ``GROUND_BELOW_AIM_MM`` below it, so the objects fill the views.
    * local x: the horizontal direction from the aim towards the mean camera position.
    """
    ids = cams.ids
    if len(ids) < 3:
        raise ValueError(f"{cams.path}: need at least 3 cameras to place the table, got {len(ids)}")
    x_axes = np.stack([cams.world_to_cam[i][0, :3] for i in ids])
    z_axes = np.stack([cams.world_to_cam[i][2, :3] for i in ids])
    centres = np.stack([geometry.camera_center(cams.world_to_cam[i]) for i in ids])
    evals, evecs = np.linalg.eigh(x_axes.T @ x_axes)
    if evals[0] > MAX_ROLL_RATIO * evals[1]:
        raise ValueError(f"{cams.path}: the cameras' x axes do not share a horizontal plane "
                         f"(eigenvalues {evals.round(3).tolist()}); cannot tell where up is")
    up = evecs[:, 0]
    proj = np.eye(3)[None] - z_axes[:, :, None] * z_axes[:, None, :]  # onto each axis' normal plane
    aim = np.linalg.solve(proj.sum(axis=0), np.einsum("nij,nj->i", proj, centres))
    if np.mean((centres - aim) @ up) < 0:
        up = -up
    toward = (centres - aim).mean(axis=0)
    x = toward - (toward @ up) * up
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(up, x), up], axis=1)
    T[:3, 3] = aim - GROUND_BELOW_AIM_MM * up
    below = np.flatnonzero((centres - T[:3, 3]) @ up <= 0)
    if below.size:
        raise ValueError(f"{cams.path}: camera(s) {[ids[i] for i in below]} lie below the table plane")
    return T


def build_scene(name: str, seed: int, cams: dtu.DTUCameras) -> SynthScene:
    """Scene ``name`` (one of :data:`SCENES`) for ``seed``, placed for the cameras ``cams``."""
    if name not in SCENES:
        raise ValueError(f"unknown synthetic scene {name!r}; choose from {', '.join(SCENES)}")
    scan_id, builder, _ = SCENES[name]
    T = snap(table_frame(cams))  # snapped: the same scene on every CPU (render module docstring)
    # Light from above and from the cameras' side, fixed in the world: Lambertian shading
    # then gives a surface point the same colour in every view.
    light = T[:3, :3] @ np.array([0.5, 0.3, 1.0])
    parts = [dataclasses.replace(p, vertices=snap(p.vertices)) for p in builder(seed)]
    return SynthScene(name, scan_id, seed, parts, T, snap(light / np.linalg.norm(light)))


def visible_gt_mesh(scene: SynthScene, renderer: Renderer, cams: dtu.DTUCameras,
                    image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The GT mesh (local mm) cut down to the triangles some camera sees (by centroid,
    see :meth:`Renderer.visible`), as DTU's scanned points cover only what its cameras
    saw: surfaces inside other parts, on the table or in unseen hollows would otherwise
    count as missed in the completeness of even a perfect reconstruction. The primitives'
    cells are at most ``shapes.CELL_MM``, which bounds what a partly seen triangle adds.
    """
    V, F = scene.gt_mesh_local()
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    seen = renderer.visible((a + b + c) / 3, np.cross(b - a, c - a), ((cams.K[v], cams.world_to_cam[v]) for v in cams.ids),
                            *image_size)
    F = F[seen]
    used = np.unique(F)
    remap = np.zeros(len(V), np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def write_synth_scene(
    name: str,
    out_dir: str | Path,
    seed: int = 0,
    width: int = 800,
    height: int = 600,
    cameras_dir: str | Path = "data/raw/dtu/scan24",
    log: Callable[[str], None] | None = print,
) -> Path:
    """Render ``name`` with every camera of ``cameras_dir`` and write the scene (DTU layout)
    with its ground truth in ``out_dir/gt`` (official DTU evaluation layout)."""
    from pipeline.evaluation.gt import write_ground_truth

    say = log or (lambda _m: None)
    t0 = time.perf_counter()
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    with atomic_dir(out_dir, "synth", inputs=(cameras_dir,)) as tmp:
        cams = dtu.load_cameras(cameras_dir)
        src_w, src_h = dtu.stored_image_size(cameras_dir)  # the size the cameras are for
        scene = build_scene(name, seed, cams)
        renderer = Renderer(scene)
        # The cameras as written (snapped: the decomposition's last bits differ between CPUs).
        K = {v: snap(geometry.scale_intrinsics(cams.K[v], width / src_w, height / src_h)) for v in cams.ids}
        cams = dtu.DTUCameras(K={v: snap(cams.K[v]) for v in cams.ids}, world_to_cam={v: snap(cams.world_to_cam[v]) for v in cams.ids},
                              norm_to_world=snap(cams.norm_to_world), path=cams.path)
        images, masks = {}, {}
        for v in cams.ids:
            hits = renderer.cast(K[v], cams.world_to_cam[v], width, height)
            images[v] = renderer.shade(hits)
            masks[v] = renderer.object_mask(hits)
        gain = 1.0
        if name in DARK_MASK_MEAN:
            grey = [np.mean(images[v][masks[v]]) for v in cams.ids if masks[v].any()]
            gain = DARK_MASK_MEAN[name] / float(np.mean(grey))
            images = {v: np.clip(img * gain, 0.0, 1.0) for v, img in images.items()}
        say(f"[synth] {name}: rendered {len(cams.ids)} views at {width}x{height} ({time.perf_counter() - t0:.1f} s)")
        v_local, tris = visible_gt_mesh(scene, renderer, cams, (src_w, src_h))
        v_world = scene.to_world(v_local)
        # Every GT triangle is seen, so the ObsMask is the GT points' voxels (the default).
        write_ground_truth(tmp / "gt", scene.scan_id, v_world, tris, scene.ground_plane(), seed=seed)
        meta = {
            "name": name,
            "scan_id": scene.scan_id,
            "seed": seed,
            "source": "synthetic",
            "units": "mm",
            "frame": "DTU world frame of the camera source",
            "stresses": SCENES[name][2],
            "cameras_from": str(cameras_dir),
            "width": width,
            "height": height,
            "exposure_gain": round(gain, 6),
        }
        if name in SUGGESTED_VIEWS:
            meta["suggested_views"] = SUGGESTED_VIEWS[name]
        dtu.write_scene_files(tmp, images, K, cams.world_to_cam, cams.norm_to_world, masks=masks, meta=meta)
    say(f"[synth] {name}: wrote {out_dir} ({time.perf_counter() - t0:.1f} s)")
    return Path(out_dir)
