"""Inputs are read strictly (issue 57): a truncated or corrupt image, mask, PLY, COLMAP model
or timing file is one error naming the file -- never a silently wrong read -- and valid
files read exactly as before."""
from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest

from pipeline import ply
from pipeline.cli import main
from pipeline.data import colmap, dtu, export
from pipeline.data.scene import SceneError
from pipeline.evaluation import gt
from pipeline.evaluation.record import TIMING_KEYS
from pipeline.evaluation.sampling import MeshError
from pipeline.init import io as init_io

REPO = Path(__file__).resolve().parents[1]
W, H = 80, 60


def _picture(h=H, w=W, seed=0):
    rng = np.random.default_rng(seed)
    ys, xs = np.mgrid[0:h, 0:w]
    img = np.stack([xs * 3 % 256, ys * 4 % 256, (xs + ys) * 2 % 256], -1) + rng.integers(0, 40, (h, w, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _cut(path: Path, keep: float = 0.5) -> Path:
    raw = path.read_bytes()
    path.write_bytes(raw[: int(len(raw) * keep)])
    return path


def _one_line_error(capsys, *names: str) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    for name in names:
        assert name in lines[0]
    return lines[0]


# ---- 1. truncated or corrupt images and masks ---------------------------------------------


def test_truncated_images_and_masks_name_the_file(tmp_path):
    img = _picture(150, 200)
    mask = np.zeros((150, 200), np.uint8)
    mask[40:100, 50:150] = 255
    for name, arr in (("view.jpg", img), ("view.png", img), ("mask.jpg", mask), ("mask.png", mask)):
        path = tmp_path / name
        assert cv2.imwrite(str(path), arr)
        _cut(path)
        read = dtu.read_mask if name.startswith("mask") else dtu.read_image
        with pytest.raises(SceneError, match=rf"{name}: image file is truncated or corrupt"):
            read(path)


def test_valid_images_and_masks_read_as_cv2_decodes_them(tmp_path):
    img = _picture()
    mask = np.zeros((H, W), np.uint8)
    mask[10:40, 20:60] = 200
    mask[45:50, 5:10] = 100
    for name in ("a.jpg", "a.png"):
        assert cv2.imwrite(str(tmp_path / name), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        plain = cv2.cvtColor(cv2.imread(str(tmp_path / name), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(dtu.read_image(tmp_path / name), plain.astype(np.float32) / 255.0)
    # grey, RGB and RGB-with-opaque-alpha masks: the grey value as cv2 gives it
    for name, arr in (("grey.png", mask), ("grey.jpg", mask), ("rgb.png", np.dstack([mask, mask // 2, mask])),
                      ("rgba_opaque.png", np.dstack([mask, mask, mask, np.full_like(mask, 255)]))):
        assert cv2.imwrite(str(tmp_path / name), arr)
        np.testing.assert_array_equal(dtu.read_mask(tmp_path / name),
                                      cv2.imread(str(tmp_path / name), cv2.IMREAD_GRAYSCALE) > 127)


# ---- 2. masks in the alpha channel --------------------------------------------------------


def test_rgba_mask_uses_its_alpha(tmp_path):
    alpha = np.zeros((H, W), np.uint8)
    alpha[15:45, 20:60] = 255
    rgba = np.dstack([np.full((H, W, 3), 255, np.uint8), alpha])  # white everywhere, the mask in alpha
    assert cv2.imwrite(str(tmp_path / "m.png"), rgba)
    m = dtu.read_mask(tmp_path / "m.png")
    np.testing.assert_array_equal(m, alpha > 127)
    assert m.mean() == pytest.approx(0.25)


# ---- 3. PLY element counts against the data -----------------------------------------------


def _mesh(n_faces=1000):
    rng = np.random.default_rng(0)
    V = rng.uniform(-1, 1, (300, 3)).astype(np.float32)
    F = rng.integers(0, 300, (n_faces, 3))
    return V, F


def _ascii_ply(V, F) -> str:
    head = ["ply", "format ascii 1.0", f"element vertex {len(V)}", "property float x", "property float y",
            "property float z", f"element face {len(F)}", "property list uchar int vertex_indices", "end_header"]
    return "\n".join(head + [" ".join(f"{c:.6f}" for c in v) for v in V] + [f"3 {a} {b} {c}" for a, b, c in F]) + "\n"


def test_ply_cut_in_the_face_list_names_the_file(tmp_path):
    V, F = _mesh()
    raw = ply.encode({k: V[:, i] for i, k in enumerate("xyz")}, F)
    binary = tmp_path / "mesh.ply"
    binary.write_bytes(raw[: len(raw) - 310 * 13])  # 13 bytes a face: 690 of 1000 faces kept
    with pytest.raises(MeshError, match=r"mesh\.ply: header declares 1000 faces, file holds 690"):
        gt.read_mesh(binary)
    text = _ascii_ply(V, F).splitlines(keepends=True)
    ascii_ply = tmp_path / "ascii.ply"
    ascii_ply.write_text("".join(text[:-310]))
    with pytest.raises(MeshError, match=r"ascii\.ply: header declares 1000 faces, file holds 690"):
        gt.read_mesh(ascii_ply)
    ascii_ply.write_text("".join(text) + "3 0 1 2\n")  # more data than declared: not silent either
    with pytest.raises(MeshError, match=r"ascii\.ply: 4 values after the 300 vertices, 1000 faces"):
        gt.read_mesh(ascii_ply)
    binary.write_bytes(raw + b"\0" * 13)
    with pytest.raises(MeshError, match=r"mesh\.ply: 13 bytes after the 300 vertices, 1000 faces"):
        gt.read_mesh(binary)
    points = tmp_path / "points.ply"
    points.write_bytes(ply.encode({k: V[:, i] for i, k in enumerate("xyz")})[:-12 * 100])
    with pytest.raises(gt.GroundTruthError, match=r"points\.ply: header declares 300 vertices, file holds 200"):
        gt.read_points(points)
    cloud = init_io.write_ply(tmp_path / "init.ply", init_io.PointCloud(
        V.astype(np.float64), np.full_like(V, 0.5), np.tile([0.0, 0.0, 1.0], (len(V), 1)), np.ones(len(V))))
    _cut(cloud, 0.75)  # the init stage's own reader says the same
    with pytest.raises(init_io.InitFormatError, match=r"init\.ply: header declares 300 vertices, file holds 2\d\d"):
        init_io.read_ply(cloud)


def test_valid_ply_reads_as_open3d_reads_it(tmp_path):
    V, F = _mesh()
    binary, ascii_ply = tmp_path / "mesh.ply", tmp_path / "ascii.ply"
    binary.write_bytes(ply.encode({k: V[:, i] for i, k in enumerate("xyz")}, F))
    ascii_ply.write_text(_ascii_ply(V, F))
    mixed = tmp_path / "mixed.ply"  # a triangle and a quad, big-endian
    mixed.write_bytes(b"ply\nformat binary_big_endian 1.0\nelement vertex 4\nproperty double x\nproperty double y\n"
                      b"property double z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
                      + np.eye(4, 3, dtype=">f8").tobytes() + b"\x03" + np.array([0, 1, 2], ">i4").tobytes()
                      + b"\x04" + np.array([0, 1, 2, 3], ">i4").tobytes())
    for path in (binary, ascii_ply, mixed):
        m = o3d.io.read_triangle_mesh(str(path))
        vertices, triangles = gt.read_mesh(path)
        np.testing.assert_array_equal(vertices, np.asarray(m.vertices))
        np.testing.assert_array_equal(triangles, np.asarray(m.triangles))
    np.testing.assert_array_equal(gt.read_points(binary), np.asarray(o3d.io.read_point_cloud(str(binary)).points))


# ---- 4. COLMAP models ---------------------------------------------------------------------


def _colmap(root: Path, binary: bool) -> Path:
    K = {v: np.array([[70.0, 0, 39.5], [0, 70.0, 29.5], [0, 0, 1]]) for v in range(3)}
    T = {}
    for v in range(3):
        T[v] = np.eye(4)
        T[v][:3, 3] = [0.1 * v, 0.0, 3.0]
    points = np.random.default_rng(0).normal(size=(50, 3))
    export.write_colmap(root, K, T, (W, H), {v: _picture(seed=v) for v in range(3)}, None, points, binary=binary)
    return root


def test_truncated_or_empty_colmap_binaries_name_the_file(tmp_path):
    src = _colmap(tmp_path / "c", binary=True)
    model = src / "sparse" / "0"
    assert colmap.read_capture(src).size == (W, H)
    originals = {name: (model / name).read_bytes() for name in ("cameras.bin", "images.bin", "points3D.bin")}
    cases = [("points3D.bin", lambda raw: raw[: len(raw) // 2], r"points3D\.bin: truncated: declares 50 points, holds"),
             ("points3D.bin", lambda raw: b"", r"points3D\.bin: empty file"),
             ("images.bin", lambda raw: b"", r"images\.bin: empty file"),
             ("images.bin", lambda raw: raw[:-100], r"images\.bin: truncated"),
             ("cameras.bin", lambda raw: raw[:-8], r"cameras\.bin: truncated in camera"),
             ("cameras.bin", lambda raw: raw + b"\0", r"cameras\.bin: 1 bytes after the records it declares")]
    for name, cut, message in cases:
        (model / name).write_bytes(cut(originals[name]))
        t0 = time.perf_counter()
        with pytest.raises(SceneError, match=message):
            colmap.read_capture(src)
        assert time.perf_counter() - t0 < 5
        (model / name).write_bytes(originals[name])


def test_colmap_text_lines_missing_columns_name_the_file_and_line(tmp_path):
    src = _colmap(tmp_path / "c", binary=False)
    model = src / "sparse" / "0"
    cases = [("cameras.txt", r"cameras\.txt: line 4: 7 columns, a PINHOLE camera needs 8"),
             ("images.txt", r"images\.txt: line 5: 9 columns, an image needs 10"),
             ("points3D.txt", r"points3D\.txt: line 4: 7 columns, a point needs 8")]
    for name, message in cases:
        original = (model / name).read_text()
        lines = original.splitlines()
        first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
        lines[first] = " ".join(lines[first].split()[:-1] if name != "points3D.txt" else lines[first].split()[:7])
        (model / name).write_text("\n".join(lines) + "\n")
        with pytest.raises(SceneError, match=message):
            colmap.read_capture(src)
        (model / name).write_text(original)
    # points3D.txt cut at a line's end: fewer points than COLMAP's header line says
    original = (model / "points3D.txt").read_text()
    (model / "points3D.txt").write_text("".join(original.splitlines(keepends=True)[:-25]))
    with pytest.raises(SceneError, match=r"points3D\.txt: says 'Number of points: 50' but holds 25"):
        colmap.read_capture(src)


# ---- 5. gcgs score --train-timing ---------------------------------------------------------


def test_score_with_a_broken_timing_file_is_one_line(tmp_path, capsys):
    surfels, meshes = tmp_path / "surfels", tmp_path / "meshes"
    surfels.mkdir()
    meshes.mkdir()
    (surfels / "train.json").write_text(json.dumps({k: 1 for k in ("iterations", "surfels_init", "surfels_final",
                                                                   "removed_degenerate", "preset", "backend",
                                                                   "masks")}))
    (meshes / "mesh.json").write_text(json.dumps({"triangles_kept": 1, "components_kept": 1, "views_virtual": 0}))
    timing, out = tmp_path / "timing.json", tmp_path / "reports" / "scan24.json"
    argv = ["score", "scan24", "--scene", str(tmp_path / "scene"), "--surfels-dir", str(surfels),
            "--mesh-dir", str(meshes), "--train-timing", str(timing), "--out", str(out),
            "--params", str(REPO / "params.yaml")]
    for content, problem in ((None, "not found"), ("{not json", "not valid JSON"),
                             (json.dumps({k: 1.0 for k in TIMING_KEYS if k != "cpu_s"}), "lack `cpu_s`")):
        if content is not None:
            timing.write_text(content)
        assert main(argv) == 1
        _one_line_error(capsys, str(timing), problem)
        assert not out.exists()


# ---- command level: gcgs prepare on a folder with a truncated image -----------------------


def test_prepare_with_a_truncated_image_is_one_line_and_writes_nothing(tmp_path, capsys):
    K = np.array([[96.0, 0, 39.5], [0, 96.0, 29.5], [0, 0, 1]])
    T = {}
    for v in range(3):
        T[v] = np.eye(4)
        T[v][:3, 3] = [v * 10.0 - 10.0, 0, 500.0]
    src = dtu.write_scene(tmp_path / "src", {v: _picture(seed=v) / 255.0 for v in range(3)}, {v: K for v in range(3)},
                          T, np.diag([100.0, 100.0, 100.0, 1.0]))
    png = src / "image" / "000001.png"
    jpg = png.with_suffix(".jpg")
    assert cv2.imwrite(str(jpg), cv2.imread(str(png)))
    png.unlink()
    _cut(jpg)
    out = tmp_path / "prepared"
    assert main(["prepare", "--src", str(src), "--out", str(out), "--views", "0", "1", "--width", "40"]) == 1
    line = _one_line_error(capsys, str(jpg), "truncated or corrupt")
    assert line.startswith("gcgs prepare: error:")
    assert not out.exists()
