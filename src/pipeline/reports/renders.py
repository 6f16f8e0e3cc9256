"""Pictures of one scene's result for the report.

``reports/renders/SCENE.png`` (:func:`scene_panels`): at the first input view, side by
side, the input image, the trained surfels' rendered colour, their rendered normals, and the
extracted mesh shaded by a headlight.

Normals are shown in the camera frame with OpenGL-style axes (x right, y up, z towards the
viewer) mapped to RGB as ``(n + 1) / 2``: a surface facing the camera is light blue.

``reports/renders/SCENE_heldout.png`` (:func:`heldout_overlay`): a few views not used for
training (the ones the ``score`` stage scores, :func:`pipeline.data.heldout.load_heldout`),
the mesh's ray-cast silhouette against the view's mask over the dimmed image: grey where both
cover a pixel, red where only the mask does (missed), blue where only the mesh does (extra),
with the mesh's mask IoU per view. Counts and IoU are taken at the held-out views' stored
size (at most the panel width); the panel is that picture scaled up.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from pipeline import atomic, geometry
from pipeline.data import dtu
from pipeline.data.heldout import HELDOUT_DIR, load_heldout
from pipeline.errors import MissingInputError
from pipeline.evaluation.gt import read_mesh
from pipeline.evaluation.heldout import iou
from pipeline.rasterizer import Camera, rasterize
from pipeline.raycast import MeshCaster
from pipeline.surfels import read_surfel_ply

PANEL_WIDTH = 400  # px; scan24's four panels make a PNG of ~0.9 MB, its held-out grid ~0.3 MB
LABELS = ("input view {view}", "surfels: colour", "surfels: normal", "mesh")
OPENCV_TO_OPENGL = np.array([1.0, -1.0, -1.0])

HELDOUT_VIEWS = 4
NEITHER, BOTH, MISSED, EXTRA = 0, 1, 2, 3  # silhouette_classes' values
CLASS_RGB = {BOTH: (0.85, 0.85, 0.85), MISSED: (1.0, 0.15, 0.1), EXTRA: (0.15, 0.45, 1.0)}
CLASS_NAMES = {BOTH: "mesh and mask", MISSED: "missed (mask only)", EXTRA: "extra (mesh only)"}
DIM = 0.45  # the image under the overlay, darkened so that the colours stand out
TINT = 0.65  # weight of a class colour over the dimmed image (the image stays faintly visible)
TEXT_RGB = (255, 255, 0)


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


def mesh_caster(mesh: str | Path | MeshCaster) -> MeshCaster:
    """A :class:`MeshCaster` of a mesh file (world mm); one already built is passed through
    (the stage builds it once for both pictures)."""
    return mesh if isinstance(mesh, MeshCaster) else MeshCaster(*read_mesh(mesh))


def _font(panel_width: int) -> tuple[float, int, int]:
    """``(font scale, thickness, line height px)`` of labels: 0.35 on 160 px panels, growing
    with wider ones so that the text stays readable but small."""
    scale = 0.35 * max(1.0, panel_width / 250)
    return scale, max(1, round(scale / 0.6)), round(12 * scale / 0.35)


def _label(panel: np.ndarray, lines: list[str], panel_width: int) -> None:
    scale, thick, step = _font(panel_width)
    rim = [(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1) if dx or dy]
    for k, text in enumerate(lines):
        # A dark rim (the text shifted by 1 px; a thicker stroke would also widen the letters'
        # spacing) keeps yellow readable on a white background.
        for (dx, dy), rgb in [(d, (0, 0, 0)) for d in rim] + [((0, 0), TEXT_RGB)]:
            cv2.putText(panel, text, (4 + dx, step * (k + 1) + dy), cv2.FONT_HERSHEY_SIMPLEX, scale, rgb, thick,
                        cv2.LINE_AA)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    return (np.clip(image, 0, 1) * 255).round().astype(np.uint8)


@torch.no_grad()
def scene_panels(scene_dir: str | Path, surfels_ply: str | Path, mesh: str | Path | MeshCaster,
                 panel_width: int = PANEL_WIDTH, background: float = 0.0, backend: str = "cpu") -> np.ndarray:
    """``(H, 4 W, 3)`` uint8 RGB: input image, surfel colour, surfel normal, mesh, at the
    prepared scene's first view, each ``panel_width`` px wide (the scene's aspect ratio)."""
    if not Path(surfels_ply).is_file():
        raise MissingInputError(f"{surfels_ply}: file not found")
    caster = mesh_caster(mesh)
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
    hits = caster.cast(K, scene.world_to_cam[0], size[1], size[0])
    mesh_rgb = headlight(hits.normal_cam, hits.depth_mm > 0, K)
    panels = []
    for image, label in zip((scene.images[0], colour, normal, mesh_rgb), LABELS):
        panel = _to_uint8(image).copy()
        _label(panel, [label.format(view=scene.view_ids[0])], panel_width)
        panels.append(panel)
    return np.concatenate(panels, axis=1)


def silhouette_classes(mesh_hit: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(H, W)`` uint8 of :data:`NEITHER`, :data:`BOTH`, :data:`MISSED` (mask only) and
    :data:`EXTRA` (mesh only) from two bool silhouettes."""
    mesh_hit, mask = np.asarray(mesh_hit, bool), np.asarray(mask, bool)
    if mesh_hit.shape != mask.shape:
        raise ValueError(f"mesh silhouette {mesh_hit.shape} and mask {mask.shape} differ in size")
    out = np.full(mask.shape, NEITHER, np.uint8)
    out[mesh_hit & mask] = BOTH
    out[mask & ~mesh_hit] = MISSED
    out[mesh_hit & ~mask] = EXTRA
    return out


def overlay_rgb(image: np.ndarray, classes: np.ndarray) -> np.ndarray:
    """``(H, W, 3)`` in [0, 1]: ``image`` dimmed by :data:`DIM`, each class's pixels tinted
    with its :data:`CLASS_RGB` (weight :data:`TINT`)."""
    out = DIM * np.clip(np.asarray(image, np.float64), 0, 1)
    for c, rgb in CLASS_RGB.items():
        sel = classes == c
        out[sel] = (1 - TINT) * out[sel] + TINT * np.asarray(rgb)
    return out


def spread_views(heldout_dirs: np.ndarray, input_dirs: np.ndarray, count: int) -> list[int]:
    """Indices of ``count`` held-out views spread around the object, from unit viewing
    directions (camera centre minus object centre): first the view farthest in angle from
    every input view (where a sparse-view reconstruction is least constrained), then each
    next one farthest from those already taken. Ties go to the lower index, so the choice
    is deterministic. Returned in ascending order."""
    n = len(heldout_dirs)
    if count >= n:
        return list(range(n))
    # Largest cosine to the nearest taken direction: the smallest is the farthest view.
    nearest = (heldout_dirs @ input_dirs.T).max(axis=1) if len(input_dirs) else np.full(n, -1.0)
    picked = [int(np.argmin(nearest))]
    nearest = np.full(n, -np.inf)
    while len(picked) < count:
        nearest = np.maximum(nearest, heldout_dirs @ heldout_dirs[picked[-1]])
        nearest[picked] = np.inf
        picked.append(int(np.argmin(nearest)))
    return sorted(picked)


@dataclass
class HeldoutView:
    """One held-out view of :func:`heldout_overlay`, at the computed size."""

    view: int
    classes: np.ndarray  # (H, W) uint8, silhouette_classes(mesh, mask)
    iou: float  # mesh silhouette vs mask
    both: int
    missed: int  # pixels of the mask the mesh does not cover
    extra: int  # pixels the mesh covers outside the mask


@dataclass
class HeldoutOverlay:
    rgb: np.ndarray  # (H, W, 3) uint8: the grid of panels and the legend
    views: list[HeldoutView]
    size: tuple[int, int]  # (width, height) at which classes and IoU were computed


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def heldout_overlay(scene_dir: str | Path, src_dir: str | Path, mesh: str | Path | MeshCaster,
                    panel_width: int = PANEL_WIDTH, count: int = HELDOUT_VIEWS, columns: int = 2) -> HeldoutOverlay:
    """The mesh's silhouette against the masks of ``count`` held-out views of ``src_dir``
    (:func:`spread_views`; the views of ``scene_dir``'s images are the training views), in a
    grid of ``columns`` panels each ``panel_width`` px wide, and a legend below.

    Raises :class:`~pipeline.data.scene.SceneError` when ``src_dir`` has no held-out view
    or no masks for them, :class:`~pipeline.errors.MissingInputError` for a missing mesh."""
    if count < 1 or columns < 1:
        raise ValueError(f"count ({count}) and columns ({columns}) must be positive")
    caster = mesh_caster(mesh)
    src_dir = Path(src_dir)
    root = src_dir / HELDOUT_DIR if (src_dir / HELDOUT_DIR).is_dir() else src_dir
    # Never upsample the stored views: the counts and IoU are of real pixels, as evaluate's.
    heldout = load_heldout(src_dir, dtu.image_ids(scene_dir), min(panel_width, dtu.stored_image_size(root)[0]))
    inputs = dtu.load_cameras(scene_dir)
    centre = heldout.norm_to_world[:3, 3]
    input_dirs = _unit(np.array([geometry.camera_center(inputs.world_to_cam[v]) for v in dtu.image_ids(scene_dir)
                                 if v in inputs.world_to_cam]).reshape(-1, 3) - centre)
    picks = spread_views(_unit(heldout.camera_centers_world_mm() - centre), input_dirs, count)
    W, H = heldout.width, heldout.height
    size = (panel_width, max(1, round(panel_width * H / W)))
    views, panels = [], []
    for m in picks:
        hit = caster.cast(heldout.K[m], heldout.world_to_cam[m], H, W).depth_mm > 0
        mask = heldout.masks[m]
        classes = silhouette_classes(hit, mask)
        v = HeldoutView(view=heldout.view_ids[m], classes=classes, iou=iou(hit, mask),
                        both=int((classes == BOTH).sum()), missed=int((classes == MISSED).sum()),
                        extra=int((classes == EXTRA).sum()))
        views.append(v)
        # Classes scale up as blocks (nearest), the image smoothly: a block is one counted pixel.
        image = cv2.resize(heldout.images[m], size,
                           interpolation=cv2.INTER_LINEAR if size[0] > W else cv2.INTER_AREA)
        panel = _to_uint8(overlay_rgb(image, cv2.resize(classes, size, interpolation=cv2.INTER_NEAREST))).copy()
        n_mask = max(1, int(mask.sum()))
        _label(panel, [f"held-out view {v.view}: mesh IoU {v.iou:.3f}",
                       f"missed {100 * v.missed / n_mask:.1f}%, extra {100 * v.extra / n_mask:.1f}% of mask"],
               panel_width)
        panels.append(panel)
    rows = -(-len(panels) // columns)
    panels += [np.zeros_like(panels[0])] * (rows * columns - len(panels))  # a short last row
    grid = np.concatenate([np.concatenate(panels[r * columns:(r + 1) * columns], 1) for r in range(rows)], 0)
    return HeldoutOverlay(rgb=np.concatenate([grid, _legend(grid.shape[1], panel_width, W, H)], 0), views=views,
                          size=(W, H))


def _legend(width: int, panel_width: int, W: int, H: int) -> np.ndarray:
    """A strip below the grid: a swatch and name per class, and what was compared."""
    scale, thick, step = _font(panel_width)
    strip = np.zeros((int(2.6 * step), width, 3), np.uint8)
    x = 4
    for c, name in CLASS_NAMES.items():
        cv2.rectangle(strip, (x, step // 4), (x + step, step), tuple(int(255 * k) for k in CLASS_RGB[c]), -1)
        cv2.putText(strip, name, (x + step + 4, step), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick,
                    cv2.LINE_AA)
        x += step + 4 + cv2.getTextSize(name, cv2.FONT_HERSHEY_SIMPLEX, scale, thick)[0][0] + 2 * step
    cv2.putText(strip, f"mesh silhouette vs mask, over the dimmed image; IoU at {W}x{H} px",
                (4, int(2.2 * step)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick, cv2.LINE_AA)
    return strip


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    ok, data = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError(f"{path}: PNG encoding failed")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic.write_bytes(path, data.tobytes())


def render_scene(scene_dir: str | Path, surfels_ply: str | Path, mesh: str | Path, out: str | Path,
                 panel_width: int = PANEL_WIDTH, background: float = 0.0, backend: str = "cpu",
                 src_dir: str | Path | None = None, heldout_out: str | Path | None = None,
                 heldout_views: int = HELDOUT_VIEWS, log=print) -> HeldoutOverlay | None:
    """Files to files: :func:`scene_panels` -> ``out`` and, with ``src_dir``,
    :func:`heldout_overlay` -> ``heldout_out``; the mesh is read once, and both pictures are
    made before either is written, so a failure leaves neither half-updated."""
    if (src_dir is None) != (heldout_out is None):
        raise ValueError("src_dir and heldout_out go together")
    caster = mesh_caster(mesh)
    rgb = scene_panels(scene_dir, surfels_ply, caster, panel_width, background, backend)
    held = heldout_overlay(scene_dir, src_dir, caster, panel_width, heldout_views) if src_dir is not None else None
    write_png(out, rgb)
    log(f"[render-scene] {scene_dir}: {rgb.shape[1]}x{rgb.shape[0]} -> {out}")
    if held is not None:
        write_png(heldout_out, held.rgb)
        ious = ", ".join(f"{v.view}: {v.iou:.3f}" for v in held.views)
        log(f"[render-scene] held-out views (mesh IoU) {ious}: {held.rgb.shape[1]}x{held.rgb.shape[0]} -> {heldout_out}")
    return held
