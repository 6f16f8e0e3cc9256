"""Synthetic scenes with exact ground truth, ray cast (Open3D) with real DTU cameras.

Frames: objects are modelled in a local frame (mm, z up, origin on the ground) and placed
in the DTU world frame (mm) of the camera source: "up" is the mean direction from the
unit-sphere centre to the camera centres (DTU cameras sit on a cap above the table), and
the ground plane lies ``GROUND_BELOW_CENTRE_MM`` below the sphere centre.
"""
from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import open3d as o3d

from pipeline import geometry
from pipeline.data import dtu
from pipeline.synth import shapes, texture

GROUND_BELOW_CENTRE_MM = 50.0
GROUND_HALF_SIZE_MM = 800.0  # rendered table square
GT_GROUND_MARGIN_MM = 40.0  # GT keeps the table within this distance of the object footprint
PLANE_ABOVE_GROUND_MM = 1.0  # completeness uses GT points above this (the object only)
BACKGROUND_RGB = (0.03, 0.03, 0.03)
AMBIENT, DIFFUSE = 0.3, 0.7

# name -> (scan id, builder, what it stresses)
SCENES: dict[str, tuple[int, Callable[[int], list[shapes.Part]], str]] = {
    "synth_textureless": (1001, shapes.textureless_blob, "a large smooth region of one plain colour"),
    "synth_relief": (1002, shapes.relief_sphere, "fine high-frequency geometric detail (~1.5 mm bumps, 3-8 mm periods)"),
    "synth_thin": (1003, shapes.thin_structures, "thin fins and rods (2-3.5 mm) and sharp box edges"),
}


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
        return points_local @ self.local_to_world[:3, :3].T + self.local_to_world[:3, 3]

    def to_local(self, points_world: np.ndarray) -> np.ndarray:
        return (points_world - self.local_to_world[:3, 3]) @ self.local_to_world[:3, :3]

    def ground_plane(self) -> np.ndarray:
        """``P`` (4,): ``[x, 1] @ P > 0`` for world points above the evaluation plane."""
        up = self.up_world
        origin = self.local_to_world[:3, 3] + PLANE_ABOVE_GROUND_MM * up
        return np.r_[up, -up @ origin]

    def gt_mesh_local(self) -> tuple[np.ndarray, np.ndarray]:
        """The object's parts plus a disk of ground around its footprint (local mm)."""
        verts, tris, n = [], [], 0
        for p in self.parts:
            verts.append(p.vertices)
            tris.append(p.triangles + n)
            n += len(p.vertices)
        allv = np.concatenate(verts)
        radius = np.linalg.norm(allv[:, :2], axis=1).max() + GT_GROUND_MARGIN_MM
        ang = np.linspace(0, 2 * np.pi, 129)[:-1]
        disk = np.c_[radius * np.cos(ang), radius * np.sin(ang), np.zeros_like(ang)]
        disk = np.r_[[[0.0, 0.0, 0.0]], disk]
        fan = np.stack([np.zeros(128, np.int64), 1 + np.arange(128), 1 + (np.arange(128) + 1) % 128], axis=1)
        verts.append(disk)
        tris.append(fan + n)
        return np.concatenate(verts), np.concatenate(tris)

    def gt_ground_radius_mm(self) -> float:
        allv = np.concatenate([p.vertices for p in self.parts])
        return float(np.linalg.norm(allv[:, :2], axis=1).max() + GT_GROUND_MARGIN_MM)


def build_scene(name: str, seed: int, cams: dtu.DTUCameras) -> SynthScene:
    if name not in SCENES:
        raise ValueError(f"unknown synthetic scene {name!r}; choose from {', '.join(SCENES)}")
    scan_id, builder, _ = SCENES[name]
    S = cams.norm_to_world
    centre = S[:3, 3]
    centres = np.stack([geometry.camera_center(cams.world_to_cam[i]) for i in cams.ids])
    up = (centres - centre).mean(axis=0)
    up /= np.linalg.norm(up)
    # Local x: the horizontal part of the first camera's x axis (a fixed, seed-free choice).
    x = cams.world_to_cam[cams.ids[0]][0, :3]
    x = x - (x @ up) * up
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, up], axis=1)
    T[:3, 3] = centre - GROUND_BELOW_CENTRE_MM * up
    light = up + 0.5 * x + 0.3 * y
    return SynthScene(name, scan_id, seed, builder(seed), T, light / np.linalg.norm(light))


class Renderer:
    """Ray caster for one synthetic scene (object parts + a textured ground square)."""

    def __init__(self, scene: SynthScene) -> None:
        self.scene = scene
        self.raycaster = o3d.t.geometry.RaycastingScene()
        self.parts_world = []  # (vertices_world, triangles, vertex_normals_world, part)
        self.object_ids: list[int] = []
        for part in scene.parts:
            v = scene.to_world(part.vertices)
            mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(part.triangles))
            mesh.compute_vertex_normals()
            gid = self.raycaster.add_triangles(v.astype(np.float32), part.triangles.astype(np.uint32))
            self.object_ids.append(gid)
            self.parts_world.append((v, part.triangles, np.asarray(mesh.vertex_normals), part))
        h = GROUND_HALF_SIZE_MM
        quad = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
        self.ground_id = self.raycaster.add_triangles(
            scene.to_world(quad).astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.uint32))

    def cast(self, K: np.ndarray, world_to_cam: np.ndarray, width: int, height: int) -> dict[str, np.ndarray]:
        """Ray cast one view. Returns ``depth`` (camera z, mm; NaN where no hit),
        ``geometry`` (id per pixel, -1 for misses), ``points`` (world mm), ``hit``, and the
        raw Open3D answer fields needed for shading."""
        ys, xs = np.mgrid[0:height, 0:width]
        pix = np.stack([xs, ys, np.ones_like(xs)], axis=-1).reshape(-1, 3).astype(np.float64)
        dirs_cam = pix @ np.linalg.inv(K).T  # z = 1: t_hit is the camera depth
        R = world_to_cam[:3, :3]
        dirs = dirs_cam @ R  # R^T d
        origin = geometry.camera_center(world_to_cam)
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], axis=1).astype(np.float32)
        ans = self.raycaster.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        depth = np.where(hit, t, np.nan)
        gid = np.where(hit, ans["geometry_ids"].numpy().astype(np.int64), -1)
        points = origin + dirs * np.where(hit, t, 0.0)[:, None]
        return {
            "depth": depth.reshape(height, width),
            "geometry": gid.reshape(height, width),
            "hit": hit.reshape(height, width),
            "points": points.reshape(height, width, 3),
            "dirs": dirs.reshape(height, width, 3),
            "primitive": ans["primitive_ids"].numpy().astype(np.int64).reshape(height, width),
            "uv": ans["primitive_uvs"].numpy().astype(np.float64).reshape(height, width, 2),
            "face_normal": ans["primitive_normals"].numpy().astype(np.float64).reshape(height, width, 3),
        }

    def shade(self, hits: dict[str, np.ndarray]) -> np.ndarray:
        """Lambertian RGB image in [0, 1] from a :meth:`cast` answer."""
        H, W = hits["depth"].shape
        rgb = np.tile(np.asarray(BACKGROUND_RGB), (H * W, 1))
        gid = hits["geometry"].ravel()
        pts = hits["points"].reshape(-1, 3)
        dirs = hits["dirs"].reshape(-1, 3)
        prim = hits["primitive"].ravel()
        uv = hits["uv"].reshape(-1, 2)
        face_n = hits["face_normal"].reshape(-1, 3)
        seed = self.scene.seed
        for k, (v, tris, vn, part) in enumerate(self.parts_world):
            sel = np.flatnonzero(gid == self.object_ids[k])
            if sel.size == 0:
                continue
            if part.smooth:
                f = tris[prim[sel]]
                u, w = uv[sel, :1], uv[sel, 1:]
                n = (1 - u - w) * vn[f[:, 0]] + u * vn[f[:, 1]] + w * vn[f[:, 2]]
            else:
                n = face_n[sel]
            rgb[sel] = self._lit(texture.albedo(part.texture, self.scene.to_local(pts[sel]), seed + k), n, dirs[sel])
        sel = np.flatnonzero(gid == self.ground_id)
        rgb[sel] = self._lit(texture.albedo("ground", self.scene.to_local(pts[sel]), seed), face_n[sel], dirs[sel])
        return np.clip(rgb, 0.0, 1.0).reshape(H, W, 3)

    def _lit(self, albedo: np.ndarray, normals: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        n = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        n = np.where((np.sum(n * dirs, axis=1) > 0)[:, None], -n, n)  # face the camera
        lambert = np.clip(n @ self.scene.light_dir_world, 0.0, None)
        return albedo * (AMBIENT + DIFFUSE * lambert)[:, None]

    def object_mask(self, hits: dict[str, np.ndarray]) -> np.ndarray:
        return np.isin(hits["geometry"], self.object_ids)


def raycast_depth(vertices_mm: np.ndarray, triangles: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
                  width: int, height: int) -> np.ndarray:
    """Camera-z depth (mm) of a world-frame mesh in one view; NaN where no surface is hit."""
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(np.asarray(vertices_mm, np.float32), np.asarray(triangles, np.uint32))
    ys, xs = np.mgrid[0:height, 0:width]
    pix = np.stack([xs, ys, np.ones_like(xs)], axis=-1).reshape(-1, 3).astype(np.float64)
    dirs = (pix @ np.linalg.inv(K).T) @ world_to_cam[:3, :3]
    origin = geometry.camera_center(world_to_cam)
    rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], axis=1).astype(np.float32)
    t = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    return np.where(np.isfinite(t), t, np.nan).reshape(height, width)


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
    cams = dtu.load_cameras(cameras_dir)
    src_w, src_h = dtu.stored_image_size(cameras_dir) if dtu.find_image_dir(Path(cameras_dir)) else (width, height)
    scene = build_scene(name, seed, cams)
    renderer = Renderer(scene)
    K = {v: geometry.scale_intrinsics(cams.K[v], width / src_w, height / src_h) for v in cams.ids}
    images, masks, observed = {}, {}, []
    ground_r = scene.gt_ground_radius_mm()
    for v in cams.ids:
        hits = renderer.cast(K[v], cams.world_to_cam[v], width, height)
        images[v] = renderer.shade(hits)
        masks[v] = renderer.object_mask(hits)
        # Observed GT surface: every other pixel's hit on the object or the GT ground disk.
        pts = hits["points"][::2, ::2][hits["hit"][::2, ::2]]
        local = scene.to_local(pts)
        on_gt = (local[:, 2] > 0.5) | (np.linalg.norm(local[:, :2], axis=1) < ground_r)
        observed.append(pts[on_gt])
    say(f"[synth] {name}: rendered {len(cams.ids)} views at {width}x{height} ({time.perf_counter() - t0:.1f} s)")
    observed_pts = np.unique(np.round(np.concatenate(observed) / 0.5), axis=0) * 0.5

    parent = Path(out_dir).resolve().parent
    parent.mkdir(parents=True, exist_ok=True)
    gt_tmp = Path(tempfile.mkdtemp(prefix=".gt.", dir=parent))
    try:
        v_local, tris = scene.gt_mesh_local()
        write_ground_truth(gt_tmp, scene.scan_id, scene.to_world(v_local), tris, scene.ground_plane(),
                           observed_points_mm=observed_pts, seed=seed)
        meta = {
            "name": name,
            "scan_id": scene.scan_id,
            "seed": seed,
            "source": "synthetic",
            "units": "world frame in mm (DTU frame of the camera source)",
            "stresses": SCENES[name][2],
            "cameras_from": str(cameras_dir),
            "width": width,
            "height": height,
        }
        dtu.write_scene(out_dir, images, K, cams.world_to_cam, cams.norm_to_world, masks=masks, meta=meta,
                        extra={"gt": gt_tmp})
    finally:
        shutil.rmtree(gt_tmp, ignore_errors=True)
    say(f"[synth] {name}: wrote {out_dir} ({time.perf_counter() - t0:.1f} s)")
    return Path(out_dir)
