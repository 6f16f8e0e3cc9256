"""Ray casting (Open3D ``RaycastingScene``) of the synthetic scenes and of plain meshes.

Rays go through pixel centres at integer coordinates (see :mod:`pipeline.geometry`) and
their directions have camera-frame z = 1, so the hit parameter ``t`` *is* the camera depth
(mm). A rigid change of frame keeps ``t``, which lets :class:`Renderer` cast in the scene's
local frame, where its textures and normals live.

The same scene gives the same bytes on any x86-64 machine: Open3D (Embree) picks other
float32 code paths on other CPUs, so only *which* triangle a ray hits is taken from it; the
hit distance, barycentrics and face normal are recomputed in float64 from that triangle
(:func:`_refine_hits`, plain IEEE arithmetic). Numbers that come out of BLAS / LAPACK /
numpy's SIMD functions (camera decompositions, the table frame, the shapes' vertices),
whose last bits differ between CPUs, are rounded to 32 bits below their column's scale
(:func:`snap`) before anything is rendered from them: a difference of a few ulps of that scale then survives only
when a value lies within them of a rounding boundary (odds ~1e-7 per value).
"""
from __future__ import annotations

import numba
import numpy as np
import open3d as o3d

from pipeline import geometry
from pipeline.raycast import MeshCaster
from pipeline.synth import shapes, texture

BACKGROUND_RGB = (0.03, 0.03, 0.03)  # DTU's black backdrop
AMBIENT, DIFFUSE = 0.3, 0.7
# Adaptive anti-aliasing (see Renderer.shade): colour step that triggers supersampling.
AA_THRESHOLD = 0.1
AA_OFFSETS = ((-0.125, -0.375), (0.375, -0.125), (0.125, 0.375), (-0.375, 0.125))
# A surface point counts as seen when nothing lies on its ray more than this before it.
VISIBILITY_TOL_MM = 0.05
SNAP_BITS = 32  # bits kept by snap(): step 2^-32 ~ 2.3e-10 of a column's scale


def snap(x: np.ndarray | float, bits: int = SNAP_BITS) -> np.ndarray:
    """``x`` (float64) rounded, ties to even, to a grid of ``2^-bits`` times its column's
    scale: numbers that differ in their last bits between machines become equal (module
    docstring).

    The scale is the power of two above the largest magnitude of the scalar, of the vector
    (1-D), or of each column (last axis) of an array. A LAPACK or BLAS result's error is
    relative to that scale, not to the entry: a camera's skew (1e-4 beside a focal length
    of 1e3) or a rotation entry near zero carries noise far above its own last bit, and a
    grid relative to the entry alone would keep it."""
    x = np.asarray(x, np.float64)
    mag = np.abs(x) if x.ndim < 2 else np.abs(x).max(axis=tuple(range(x.ndim - 1)))
    if x.ndim == 1:
        mag = mag.max(initial=0.0)
    quantum = np.ldexp(1.0, np.frexp(mag)[1] - bits)  # a power of two: the division is exact
    return np.round(x / quantum) * quantum


def pixel_to_ray(K: np.ndarray, world_to_cam: np.ndarray, frame_to_world: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(origin (3,), A (3, 3))`` such that pixel ``(x, y)`` casts the ray
    ``origin + t * A @ [x, y, 1]`` in the frame ``frame_to_world`` (4x4 rigid; ``None``:
    the world frame), with ``t`` the camera depth in mm."""
    R = world_to_cam[:3, :3]
    A = R.T @ np.linalg.inv(K)  # pixel -> world direction with camera z = 1
    origin = geometry.camera_center(world_to_cam)
    if frame_to_world is not None:
        Rf = frame_to_world[:3, :3]
        A = Rf.T @ A
        origin = Rf.T @ (origin - frame_to_world[:3, 3])
    return snap(origin), snap(A)


@numba.njit(cache=True, parallel=True)
def make_rays(origin: np.ndarray, A: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """``(N, 6)`` float32 Open3D rays through the pixel coordinates ``xs``, ``ys`` (1-D)."""
    rays = np.empty((xs.size, 6), np.float32)
    for n in numba.prange(xs.size):
        for c in range(3):
            rays[n, c] = origin[c]
            rays[n, 3 + c] = A[c, 0] * xs[n] + A[c, 1] * ys[n] + A[c, 2]
    return rays


def grid_rays(origin: np.ndarray, A: np.ndarray, width: int, height: int) -> np.ndarray:
    """Rays through every pixel centre, row-major."""
    xs = np.tile(np.arange(width, dtype=np.float64), height)
    ys = np.repeat(np.arange(height, dtype=np.float64), width)
    return make_rays(origin, A, xs, ys)


@numba.njit(cache=True)
def _needs_supersampling(rgb: np.ndarray, gid: np.ndarray, threshold: float) -> np.ndarray:
    """Pixels with a 4-neighbour on another geometry or differing by > ``threshold`` in
    some channel (both pixels of such a pair are marked)."""
    H, W = gid.shape
    out = np.zeros((H, W), np.bool_)
    for y in range(H):
        for x in range(W):
            for ny, nx in ((y, x + 1), (y + 1, x)):
                if ny >= H or nx >= W:
                    continue
                step = gid[y, x] != gid[ny, nx]
                for c in range(3):
                    step = step or abs(rgb[y, x, c] - rgb[ny, nx, c]) > threshold
                if step:
                    out[y, x] = True
                    out[ny, nx] = True
    return out


def raycast_depth(vertices_mm: np.ndarray, triangles: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray,
                  width: int, height: int) -> np.ndarray:
    """Exact camera-z depth (mm, ``(height, width)`` float64) of a world-frame mesh in one
    view, 0 where the pixel-centre ray hits nothing (the project's "no depth", see
    :class:`pipeline.init.io.DepthMap`)."""
    return MeshCaster(vertices_mm, triangles).cast(K, world_to_cam, height, width).depth_mm


@numba.njit(cache=True, parallel=True)
def _refine_hits(rays, gid, prim, t_caster, tri_offset, triangles, vertices):
    """Hit distance ``t``, barycentrics ``(u, v)`` (weights of vertices 1 and 2) and face
    normal ``cross(b - a, c - a)`` of each ray's hit triangle, in float64 from the
    triangle's vertices (Moller-Trumbore), so they do not depend on the ray caster's
    float32 code path. ``t_caster`` is kept where the triangle is degenerate for the ray."""
    n = rays.shape[0]
    t = np.full(n, np.inf)
    uv = np.zeros((n, 2))
    normal = np.zeros((n, 3))
    for i in numba.prange(n):
        g = gid[i]
        if g < 0:
            continue
        f = tri_offset[g] + prim[i]
        a, b, c = vertices[triangles[f, 0]], vertices[triangles[f, 1]], vertices[triangles[f, 2]]
        e1x, e1y, e1z = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        e2x, e2y, e2z = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        dx, dy, dz = np.float64(rays[i, 3]), np.float64(rays[i, 4]), np.float64(rays[i, 5])
        px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
        det = e1x * px + e1y * py + e1z * pz
        normal[i, 0], normal[i, 1], normal[i, 2] = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
        if det == 0.0:
            t[i] = t_caster[i]
            continue
        sx, sy, sz = np.float64(rays[i, 0]) - a[0], np.float64(rays[i, 1]) - a[1], np.float64(rays[i, 2]) - a[2]
        qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
        uv[i, 0] = (sx * px + sy * py + sz * pz) / det
        uv[i, 1] = (dx * qx + dy * qy + dz * qz) / det
        t[i] = (e2x * qx + e2y * qy + e2z * qz) / det
    return t, uv, normal


@numba.njit(cache=True, parallel=True)
def _shade_kernel(rays, t, gid, prim, uv, face_normal, triangles, vertex_normals, tri_offset, smooth, kind, seed,
                  palettes, light, background, ambient, diffuse):
    """Colour ``(N, 3)`` of traced rays: albedo at the hit point times Lambertian shading.

    Per geometry id ``g``: triangles ``tri_offset[g]:`` of the concatenated arrays,
    ``smooth[g]`` (interpolate vertex normals, else the face normal), texture ``kind[g]``,
    ``seed[g]``, ``palettes[g]``.
    """
    n_rays = rays.shape[0]
    out = np.empty((n_rays, 3))
    for i in numba.prange(n_rays):
        g = gid[i]
        if g < 0:
            out[i, 0], out[i, 1], out[i, 2] = background[0], background[1], background[2]
            continue
        dx, dy, dz = rays[i, 3], rays[i, 4], rays[i, 5]
        if smooth[g]:  # barycentric (u, v) weight vertices 1 and 2
            f = tri_offset[g] + prim[i]
            u, v = uv[i, 0], uv[i, 1]
            va, vb, vc = triangles[f, 0], triangles[f, 1], triangles[f, 2]
            w = 1 - u - v
            nx = w * vertex_normals[va, 0] + u * vertex_normals[vb, 0] + v * vertex_normals[vc, 0]
            ny = w * vertex_normals[va, 1] + u * vertex_normals[vb, 1] + v * vertex_normals[vc, 1]
            nz = w * vertex_normals[va, 2] + u * vertex_normals[vb, 2] + v * vertex_normals[vc, 2]
        else:
            nx, ny, nz = face_normal[i, 0], face_normal[i, 1], face_normal[i, 2]
        if nx * dx + ny * dy + nz * dz > 0:  # the side facing the camera
            nx, ny, nz = -nx, -ny, -nz
        norm = max(np.sqrt(nx * nx + ny * ny + nz * nz), 1e-12)
        lambert = max(0.0, (nx * light[0] + ny * light[1] + nz * light[2]) / norm)
        r, gr, bl = texture.albedo(kind[g], rays[i, 0] + t[i] * dx, rays[i, 1] + t[i] * dy, rays[i, 2] + t[i] * dz,
                                  seed[g], palettes[g])
        shading = ambient + diffuse * lambert
        out[i, 0] = min(1.0, r * shading)
        out[i, 1] = min(1.0, gr * shading)
        out[i, 2] = min(1.0, bl * shading)
    return out


class Renderer:
    """Ray caster and shader of one :class:`~pipeline.synth.scenes.SynthScene` (its object
    parts and a textured ground square), working in the scene's local frame (mm)."""

    def __init__(self, scene, ground_half_size_mm: float = 800.0) -> None:
        self.scene = scene
        self.raycaster = o3d.t.geometry.RaycastingScene()
        h = ground_half_size_mm
        ground = shapes.Part(np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]]),
                             np.array([[0, 1, 2], [0, 2, 3]]), "ground", smooth=False)
        tris, normals, verts, offsets, n_vert, n_tri = [], [], [], [], 0, 0
        for part in [*scene.parts, ground]:
            verts.append(part.vertices)
            gid = self.raycaster.add_triangles(part.vertices.astype(np.float32), part.triangles.astype(np.uint32))
            assert gid == len(offsets)  # Open3D numbers geometries 0, 1, ... in order
            mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(part.vertices),
                                             o3d.utility.Vector3iVector(part.triangles))
            normals.append(snap(np.asarray(mesh.compute_vertex_normals().vertex_normals)))
            tris.append(part.triangles + n_vert)
            offsets.append(n_tri)
            n_vert += len(part.vertices)
            n_tri += len(part.triangles)
        self.object_ids = list(range(len(scene.parts)))
        self.ground_id = len(scene.parts)
        parts = [*scene.parts, ground]
        self._vertices = np.ascontiguousarray(np.concatenate(verts), np.float64)
        # Object part k is textured with seed + k, the ground with the seed.
        seeds = [scene.seed + k for k in range(len(scene.parts))] + [scene.seed]
        self._kernel_args = (
            np.concatenate(tris).astype(np.int64),
            np.concatenate(normals),
            np.array(offsets, np.int64),
            np.array([p.smooth for p in parts]),
            np.array([texture.KINDS[p.texture] for p in parts], np.int64),
            np.array(seeds, np.int64),
            np.stack([texture.palette(sd) for sd in seeds]),
            scene.local_to_world[:3, :3].T @ scene.light_dir_world,
            np.asarray(BACKGROUND_RGB, np.float64),
            AMBIENT,
            DIFFUSE,
        )

    def _trace(self, rays: np.ndarray) -> dict[str, np.ndarray]:
        ans = self.raycaster.cast_rays(o3d.core.Tensor(rays))
        t_caster = ans["t_hit"].numpy()
        geometry = np.where(np.isfinite(t_caster), ans["geometry_ids"].numpy().astype(np.int64), -1)
        primitive = ans["primitive_ids"].numpy().astype(np.int64)
        t, uv, face_normal = _refine_hits(rays, geometry, primitive, t_caster.astype(np.float64),
                                          self._kernel_args[2], self._kernel_args[0], self._vertices)
        return {"t": t, "geometry": geometry, "primitive": primitive, "uv": uv, "face_normal": face_normal}

    def _shade_samples(self, rays: np.ndarray, tr: dict[str, np.ndarray]) -> np.ndarray:
        return _shade_kernel(rays, tr["t"], tr["geometry"], tr["primitive"], tr["uv"], tr["face_normal"],
                             *self._kernel_args)

    def cast(self, K: np.ndarray, world_to_cam: np.ndarray, width: int, height: int) -> dict[str, np.ndarray]:
        """Ray cast one view through the pixel centres. Returns ``depth`` (camera z, mm;
        0 where nothing is hit), ``geometry`` (geometry id per pixel, -1 for misses),
        ``hit`` and what :meth:`shade` and :meth:`points_local` need."""
        origin, A = pixel_to_ray(K, world_to_cam, self.scene.local_to_world)
        rays = grid_rays(origin, A, width, height)
        tr = self._trace(rays)
        hit = tr["geometry"] >= 0
        return {
            "depth": np.where(hit, tr["t"], 0.0).astype(np.float64).reshape(height, width),
            "geometry": tr["geometry"].reshape(height, width),
            "hit": hit.reshape(height, width),
            "_trace": tr,
            "_rays": rays,
            "_camera": (origin, A),
        }

    @staticmethod
    def points_local(hits: dict[str, np.ndarray], where: np.ndarray) -> np.ndarray:
        """Hit points ``(N, 3)`` (scene's local frame, mm, float64) of the pixels ``where``
        (a bool ``(H, W)`` mask of hit pixels)."""
        rays, t = hits["_rays"][where.ravel()], hits["_trace"]["t"][where.ravel()]
        return rays[:, :3] + t[:, None] * rays[:, 3:]

    def object_mask(self, hits: dict[str, np.ndarray]) -> np.ndarray:
        """Pixels whose centre ray hits the object (not the ground)."""
        return (hits["geometry"] >= 0) & (hits["geometry"] != self.ground_id)

    def shade(self, hits: dict[str, np.ndarray]) -> np.ndarray:
        """RGB image (float64, [0, 1]) of a :meth:`cast` answer.

        Pixels on a silhouette (a 4-neighbour sees another geometry) or with a colour
        step above ``AA_THRESHOLD`` (sharp creases, occlusion within a part) are replaced
        by the mean of 4 rotated-grid samples, like a camera integrating over the pixel.
        """
        H, W = hits["depth"].shape
        rgb = self._shade_samples(hits["_rays"], hits["_trace"]).reshape(H, W, 3)
        edge = _needs_supersampling(rgb, hits["geometry"], AA_THRESHOLD)
        ys, xs = np.nonzero(edge)
        if len(xs):
            origin, A = hits["_camera"]
            rays = np.concatenate([make_rays(origin, A, xs + ox, ys + oy) for ox, oy in AA_OFFSETS])
            sub = self._shade_samples(rays, self._trace(rays)).reshape(len(AA_OFFSETS), len(xs), 3)
            rgb[ys, xs] = sub.mean(axis=0)
        return rgb

    def visible(self, points: np.ndarray, normals: np.ndarray, cameras, width: int, height: int) -> np.ndarray:
        """Which surface points ``(N, 3)`` (local frame, mm) with outward ``normals`` some
        camera sees: in front of it and inside its ``width x height`` image, on a face
        turned towards it (so closed parts hide their far side), and with nothing of the
        scene (object or table) on the ray more than ``VISIBILITY_TOL_MM`` before it.

        ``cameras``: iterable of ``(K, world_to_cam)`` for images of that size.
        """
        points = np.ascontiguousarray(points, np.float64)
        normals = np.ascontiguousarray(normals, np.float64)
        seen = np.zeros(len(points), bool)
        for K, world_to_cam in cameras:
            origin, A = pixel_to_ray(K, world_to_cam, self.scene.local_to_world)
            idx, rays = _visibility_rays(points, normals, np.flatnonzero(~seen), origin, np.linalg.inv(A),
                                         width, height, VISIBILITY_TOL_MM)
            blocked = self.raycaster.test_occlusions(o3d.core.Tensor(rays), tfar=1.0).numpy()
            seen[idx[~blocked]] = True
        return seen


@numba.njit(cache=True)
def _visibility_rays(points, normals, todo, origin, A_inv, width, height, tol_mm):
    """Candidates of :meth:`Renderer.visible` for one camera: indices into ``points`` and
    rays from the camera stopping ``tol_mm`` short of each point (``t`` in [0, 1])."""
    idx = np.empty(todo.size, np.int64)
    rays = np.empty((todo.size, 6), np.float32)
    n = 0
    for k in range(todo.size):
        i = todo[k]
        d0, d1, d2 = points[i, 0] - origin[0], points[i, 1] - origin[1], points[i, 2] - origin[2]
        if d0 * normals[i, 0] + d1 * normals[i, 1] + d2 * normals[i, 2] >= 0:  # faces away
            continue
        z = A_inv[2, 0] * d0 + A_inv[2, 1] * d1 + A_inv[2, 2] * d2
        if z <= 0:
            continue
        x = (A_inv[0, 0] * d0 + A_inv[0, 1] * d1 + A_inv[0, 2] * d2) / z
        y = (A_inv[1, 0] * d0 + A_inv[1, 1] * d1 + A_inv[1, 2] * d2) / z
        if x < -0.5 or x >= width - 0.5 or y < -0.5 or y >= height - 0.5:
            continue
        scale = 1.0 - tol_mm / np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        idx[n] = i
        rays[n, 0], rays[n, 1], rays[n, 2] = origin[0], origin[1], origin[2]
        rays[n, 3], rays[n, 4], rays[n, 5] = d0 * scale, d1 * scale, d2 * scale
        n += 1
    return idx[:n], rays[:n]
