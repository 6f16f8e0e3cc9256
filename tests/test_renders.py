"""The held-out picture of ``gcgs render-scene`` (:func:`pipeline.reports.renders.heldout_overlay`):
the mesh's silhouette against the masks of held-out views, and the panel sizes of both pictures.

The scene: a flat rectangle (two triangles) 100 mm in front of cameras that only translate
(identity rotation, f = 100 px), so one mm is one pixel and the rectangle's edges, at half
pixels, cover an exactly known block of pixel centres; each view's mask is another block.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.cli import main
from pipeline.data import dtu
from pipeline.data.scene import SceneError
from pipeline.errors import MissingInputError
from pipeline.evaluation import gt
from pipeline.optimize.seed import init_params
from pipeline.reports import renders
from pipeline.reports.renders import BOTH, EXTRA, MISSED, NEITHER
from pipeline.surfels import write_surfel_ply

W, H = 100, 75
K = np.array([[100.0, 0, 50], [0, 100.0, 37], [0, 0, 1]])
DEPTH = 100.0  # mm from every camera (they only translate in x and y)
RECT = (-10.5, 10.5, -5.5, 12.5)  # mesh: x0, x1, y0, y1 in mm, at half pixels in every view
CENTRE = np.array([0.0, 0.0, DEPTH])
INPUTS = {10: (0, 0), 11: (3, 0)}
HELDOUT = {0: (-8, -6), 1: (-7, -6), 2: (8, -6), 3: (0, 8), 4: (1, 8), 5: (-8, 7), 6: (8, 8), 7: (2, 1)}
GREY = 128 / 255  # the images' value, exact in 8 bits
LABEL_ROWS = 20  # rows (at W x H) the panel labels may cover; every silhouette lies below


def world_to_cam(t) -> np.ndarray:
    T = np.eye(4)
    T[:2, 3] = -np.asarray(t, float)
    return T


def mesh_silhouette(t) -> np.ndarray:
    """Pixel centres whose ray meets the rectangle, from the pinhole model directly."""
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    X = (xs - K[0, 2]) * DEPTH / K[0, 0] + t[0]
    Y = (ys - K[1, 2]) * DEPTH / K[1, 1] + t[1]
    x0, x1, y0, y1 = RECT
    return (X > x0) & (X < x1) & (Y > y0) & (Y < y1)


def mask_of(view: int) -> np.ndarray:
    """A block overlapping the mesh's silhouette partly, different in every view."""
    m = np.zeros((H, W), bool)
    m[28 + view:56, 30 + 2 * view:62 + view] = True
    return m


def write_scan(root, views: dict, masks: bool = True) -> None:
    norm_to_world = np.diag([30.0, 30.0, 30.0, 1.0])  # a 30 mm sphere around the rectangle
    norm_to_world[:3, 3] = CENTRE
    cams = {**INPUTS, **HELDOUT}
    dtu.write_scene(root, {v: np.full((H, W, 3), GREY, np.float32) for v in views},
                    {v: K for v in cams}, {v: world_to_cam(t) for v, t in cams.items()}, norm_to_world,
                    masks={v: mask_of(v) for v in views} if masks else None)


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    """``(root)``: ``scene/`` (the inputs), ``src/`` (every view, masks; the synthetic
    scenes' layout), ``src_dtu/`` (the inputs, held-out views in ``heldout/``; scan24's),
    ``mesh.ply`` (the rectangle) and ``surfels.ply`` (surfels on it)."""
    root = tmp_path_factory.mktemp("renders")
    write_scan(root / "scene", INPUTS, masks=False)
    write_scan(root / "src", {**INPUTS, **HELDOUT})
    write_scan(root / "src_dtu", INPUTS)
    write_scan(root / "src_dtu" / "heldout", HELDOUT)
    x0, x1, y0, y1 = RECT
    V = np.array([[x0, y0, DEPTH], [x1, y0, DEPTH], [x1, y1, DEPTH], [x0, y1, DEPTH]])
    gt.write_ply_mesh(root / "mesh.ply", V, np.array([[0, 1, 2], [0, 2, 3]]))
    xs, ys = np.meshgrid(np.linspace(x0 + 1, x1 - 1, 12), np.linspace(y0 + 1, y1 - 1, 12))
    points = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, DEPTH)], 1)
    normals = np.tile([0.0, 0.0, -1.0], (len(points), 1))
    params = init_params((points - CENTRE) / 30.0, normals, np.full((len(points), 3), 0.6), 0, 0.99,
                         np.random.default_rng(0))
    write_surfel_ply(root / "surfels.ply", params, dtu.load_cameras(root / "scene").norm_to_world)
    return root


@pytest.mark.parametrize("src", ["src", "src_dtu"])
def test_colours_are_the_mesh_silhouette_against_the_mask(scan, src):
    out = renders.heldout_overlay(scan / "scene", scan / src, scan / "mesh.ply")
    assert out.size == (W, H) and len(out.views) == renders.HELDOUT_VIEWS
    assert {v.view for v in out.views} <= set(HELDOUT)  # never a training view
    scale = renders.PANEL_WIDTH // W
    for k, v in enumerate(out.views):
        sil, mask = mesh_silhouette(HELDOUT[v.view]), mask_of(v.view)
        assert sil[:LABEL_ROWS].sum() == 0 and mask[:LABEL_ROWS].sum() == 0
        assert v.both == (sil & mask).sum() > 0
        assert v.missed == (mask & ~sil).sum() > 0
        assert v.extra == (sil & ~mask).sum() > 0
        assert v.iou == pytest.approx((sil & mask).sum() / (sil | mask).sum())
        want = np.select([sil & mask, mask & ~sil, sil & ~mask], [BOTH, MISSED, EXTRA], NEITHER)
        assert np.array_equal(v.classes, want)
        # The picture: each counted pixel is a scale x scale block of its class's colour.
        row, col = divmod(k, 2)
        panel = out.rgb[row * H * scale:(row + 1) * H * scale, col * W * scale:(col + 1) * W * scale]
        colours = {c: (renders.overlay_rgb(np.full((1, 1, 3), GREY), np.full((1, 1), c, np.uint8))[0, 0] * 255).round()
                   for c in (NEITHER, BOTH, MISSED, EXTRA)}
        below = panel[LABEL_ROWS * scale:].astype(float)
        for c, rgb in colours.items():
            assert (np.abs(below - rgb).max(-1) < 1).sum() == scale * scale * (want[LABEL_ROWS:] == c).sum()


def test_views_are_spread_and_deterministic():
    def dirs(degrees):
        a = np.radians(degrees)
        return np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)

    views = dirs([0, 10, 20, 95, 180, 250, 280])
    # First the view opposite the input (180), then the one farthest from it (0), then the
    # one farthest from both (95: 85 degrees off), then 280 (80 degrees off).
    assert renders.spread_views(views, dirs([0]), 3) == [0, 3, 4]
    assert renders.spread_views(views, dirs([0]), 4) == [0, 3, 4, 6]
    assert renders.spread_views(views, dirs([0]), 9) == list(range(7))
    assert renders.spread_views(dirs([0, 90, 90]), dirs([0]), 1) == [1]  # a tie: the lower index


def test_panels_are_at_least_400_px_wide(scan):
    assert renders.PANEL_WIDTH >= 400
    rgb = renders.scene_panels(scan / "scene", scan / "surfels.ply", scan / "mesh.ply")
    assert rgb.shape == (round(renders.PANEL_WIDTH * H / W), 4 * renders.PANEL_WIDTH, 3)
    mesh = rgb[LABEL_ROWS * 4:, 3 * renders.PANEL_WIDTH:]
    assert mesh.max() > 0  # the rectangle, lit from the camera
    held = renders.heldout_overlay(scan / "scene", scan / "src", scan / "mesh.ply", count=3)
    assert held.rgb.shape[1] == 2 * renders.PANEL_WIDTH and held.rgb.shape[0] > 2 * round(renders.PANEL_WIDTH * H / W)


def test_command_writes_both_pictures(scan, tmp_path, capsys):
    out, held = tmp_path / "r" / "s.png", tmp_path / "r" / "s_heldout.png"
    assert main(["render-scene", "--scene", str(scan / "scene"), "--surfels", str(scan / "surfels.ply"),
                 "--mesh", str(scan / "mesh.ply"), "--out", str(out), "--src", str(scan / "src_dtu"),
                 "--heldout-out", str(held)]) == 0
    assert cv2.imread(str(out)).shape == (300, 1600, 3) and cv2.imread(str(held)).shape[1] == 800
    assert 0 < out.stat().st_size < 1_500_000 and 0 < held.stat().st_size < 1_500_000
    assert "mesh IoU" in capsys.readouterr().out


def test_bad_input_names_the_file(scan, tmp_path, capsys):
    with pytest.raises(MissingInputError, match="nothing.ply: file not found"):
        renders.heldout_overlay(scan / "scene", scan / "src", tmp_path / "nothing.ply")
    out, held = tmp_path / "s.png", tmp_path / "s_heldout.png"
    args = ["render-scene", "--scene", str(scan / "scene"), "--surfels", str(scan / "surfels.ply"),
            "--out", str(out), "--src", str(scan / "src"), "--heldout-out", str(held)]
    assert main([*args, "--mesh", str(tmp_path / "missing.ply")]) == 1
    assert "missing.ply: file not found" in capsys.readouterr().err
    # Held-out views without masks, or none at all (every image a training view).
    write_scan(tmp_path / "nomask", {**INPUTS, **HELDOUT}, masks=False)
    with pytest.raises(SceneError, match="nomask.*need masks"):
        renders.heldout_overlay(scan / "scene", tmp_path / "nomask", scan / "mesh.ply")
    with pytest.raises(SceneError, match="no held-out view"):
        renders.heldout_overlay(scan / "scene", scan / "scene", scan / "mesh.ply")
    assert main([*args[:-2], "--mesh", str(scan / "mesh.ply")]) == 1
    assert "--src and --heldout-out go together" in capsys.readouterr().err
    assert not out.exists() and not held.exists()
