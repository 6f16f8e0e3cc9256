"""A user's data is never lost and bad input is one line before any work (issue 17), through
the ``gcgs`` commands as a user runs them: outputs onto inputs, user folders or the current
folder refused with the inputs intact byte for byte, a second writer refused, sizes checked
on every image, another scene's outputs refused, degenerate results written nowhere."""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pipeline import cli
from pipeline.atomic import MARKER, atomic_dir
from pipeline.data import dtu
from pipeline.init.io import PointCloud, write_ply
from pipeline.runs.optimize import default_side_paths
from pipeline.optimize.seed import init_params
from pipeline.surfels import write_surfel_ply
from test_atomic import tree_digest

REPO = Path(__file__).resolve().parents[1]
PARAMS = str(REPO / "params.yaml")


def _scan(root: Path, seed: int = 0, width: int = 80, height: int = 60, n: int = 6) -> Path:
    """A DTU-layout scan of ``n`` views (ids 0..n-1) with masks, cameras around a sphere."""
    rng = np.random.default_rng(seed)
    K = np.array([[1.5 * width, 0, (width - 1) / 2], [0, 1.5 * width, (height - 1) / 2], [0, 0, 1]])
    Ts = {}
    for v in range(n):
        a = math.radians(10 * (v - n / 2))
        T = np.eye(4)
        T[:3, :3] = [[math.cos(a), 0, -math.sin(a)], [0, 1, 0], [math.sin(a), 0, math.cos(a)]]
        T[:3, 3] = [0, 0, 500.0]
        Ts[v] = T
    mask = np.zeros((height, width), bool)
    mask[height // 4:3 * height // 4, width // 4:3 * width // 4] = True
    return dtu.write_scene(root, {v: rng.uniform(size=(height, width, 3)) for v in range(n)}, {v: K for v in range(n)},
                           Ts, np.diag([100.0, 100.0, 100.0, 1.0]), masks={v: mask for v in range(n)},
                           meta={"name": root.name})


def _gcgs(capsys, *argv) -> tuple[int, str]:
    rc = cli.main([str(a) for a in argv])
    return rc, capsys.readouterr().err


def _prepare(capsys, src, out, *extra) -> tuple[int, str]:
    return _gcgs(capsys, "prepare", "--src", src, "--out", out, "--views", 0, 1, 2, "--width", 40, "--params", PARAMS,
                 *extra)


def _one_error_line(err: str, command: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"gcgs {command}: error: "), err
    return lines[0]


# -- data loss -----------------------------------------------------------------------------

@pytest.mark.parametrize("where", ["same", "inside"])
def test_prepare_onto_its_source_is_refused(tmp_path, capsys, where):
    src = _scan(tmp_path / "src")
    before = tree_digest(src)
    rc, err = _prepare(capsys, src, src if where == "same" else src / "image")
    assert rc == 1 and "destroy the input" in _one_error_line(err, "prepare")
    assert tree_digest(src) == before


def test_prepare_into_a_user_folder_is_refused(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    rc, err = _prepare(capsys, src, mine)
    assert rc == 1 and "not written by gcgs" in _one_error_line(err, "prepare")
    assert tree_digest(mine) == {"notes.txt": tree_digest(mine)["notes.txt"]} and (mine / "notes.txt").read_text() == "mine"


def test_prepare_into_the_current_folder_is_refused(tmp_path, capsys, monkeypatch):
    src = _scan(tmp_path / "src")
    work = tmp_path / "work"
    work.mkdir()
    (work / "keep.txt").write_text("keep")
    monkeypatch.chdir(work)
    for out in (".", ".."):
        rc, err = _prepare(capsys, src, out)
        assert rc == 1 and "current folder" in _one_error_line(err, "prepare")
    assert (work / "keep.txt").read_text() == "keep" and sorted(p.name for p in work.iterdir()) == ["keep.txt"]


def test_prepare_replaces_its_own_output(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    assert _prepare(capsys, src, tmp_path / "scene")[0] == 0
    assert (tmp_path / "scene" / MARKER).is_file()
    rc, _ = _gcgs(capsys, "prepare", "--src", src, "--out", tmp_path / "scene", "--views", 1, 2, "--width", 40,
                  "--params", PARAMS)
    assert rc == 0 and dtu.image_ids(tmp_path / "scene") == [1, 2]


def test_init_onto_the_scene_or_another_output_is_refused(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    assert _prepare(capsys, src, tmp_path / "scene")[0] == 0
    assert _prepare(capsys, src, tmp_path / "other")[0] == 0
    for out, why in ((tmp_path / "scene", "destroy the input"), (tmp_path / "other", "holds a gcgs scene output")):
        before = tree_digest(out)
        rc, err = _gcgs(capsys, "init", "--scene", tmp_path / "scene", "--backend", "random", "--out-dir", out,
                        "--params", PARAMS)
        assert rc == 1 and why in _one_error_line(err, "init")
        assert tree_digest(out) == before


def test_a_second_writer_of_the_same_output_is_refused(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    out = tmp_path / "scene"
    with atomic_dir(out, "scene") as tmp:  # another writer holds the output
        rc, err = _prepare(capsys, src, out)
        (tmp / "first").write_text("1")
    assert rc == 1 and "another gcgs process is writing" in _one_error_line(err, "prepare")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "first"]


# -- silently wrong results ----------------------------------------------------------------

def test_an_odd_sized_unselected_image_is_named(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    cv2.imwrite(str(src / "image" / "000005.png"), np.zeros((120, 160, 3), np.uint8))  # not a selected view
    rc, err = _prepare(capsys, src, tmp_path / "out")
    assert rc == 1 and "000005.png: size 160x120 differs" in _one_error_line(err, "prepare")
    assert not (tmp_path / "out").exists()


def test_a_mask_of_another_aspect_is_named(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    cv2.imwrite(str(src / "mask" / "004.png"), np.full((60, 60), 255, np.uint8))  # a held-out view's mask
    rc, err = _prepare(capsys, src, tmp_path / "out")
    assert rc == 1 and "004.png: mask is 60x60" in _one_error_line(err, "prepare")
    assert not (tmp_path / "out").exists()


def test_an_upsampled_scene_is_made_with_a_warning(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    rc, err = _gcgs(capsys, "prepare", "--src", src, "--out", tmp_path / "out", "--views", 0, 1, "--width", 160,
                    "--params", PARAMS)
    assert rc == 0 and "gcgs: warning:" in err and "upsamples" in err


@pytest.mark.parametrize("width, why", [(1, "below 16 px"), (100000, "upsamples"), (8, "below 16 px")])
def test_absurd_sizes_are_one_line(tmp_path, capsys, width, why):
    src = _scan(tmp_path / "src")
    rc, err = _gcgs(capsys, "prepare", "--src", src, "--out", tmp_path / "out", "--views", 0, 1, "--width", width,
                    "--params", PARAMS)
    assert rc == 1 and why in _one_error_line(err, "prepare")
    assert not (tmp_path / "out").exists()


def test_a_single_view_is_refused_by_prepare(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    rc, err = _gcgs(capsys, "prepare", "--src", src, "--out", tmp_path / "out", "--views", 3, "--width", 40,
                    "--params", PARAMS)
    assert rc == 1 and "at least 2" in _one_error_line(err, "prepare")


def test_outputs_of_another_scene_are_refused(tmp_path, capsys):
    for name, seed in (("a", 0), ("b", 1)):  # same size and cameras, other pixels
        src = _scan(tmp_path / f"src_{name}", seed=seed)
        assert _prepare(capsys, src, tmp_path / f"scene_{name}")[0] == 0
        assert _gcgs(capsys, "init", "--scene", tmp_path / f"scene_{name}", "--backend", "random", "--out-dir",
                     tmp_path / f"init_{name}", "--params", PARAMS)[0] == 0
    rc, err = _gcgs(capsys, "priors", "--scene", tmp_path / "scene_a", "--init-dir", tmp_path / "init_b",
                    "--normals", "none", "--out-dir", tmp_path / "priors", "--params", PARAMS)
    assert rc == 1 and "computed from another scene" in _one_error_line(err, "priors")
    rc, err = _gcgs(capsys, "optimize", "--scene", tmp_path / "scene_a", "--init-dir", tmp_path / "init_b",
                    "--priors-dir", tmp_path / "none", "--out-dir", tmp_path / "surfels", "--params", PARAMS,
                    "--no-progress")
    assert rc == 1 and "init_b/init.json: this init output was computed from another scene" in _one_error_line(
        err, "optimize")
    assert not (tmp_path / "priors").exists() and not (tmp_path / "surfels").exists()


# -- degenerate results and one-line errors ------------------------------------------------

@pytest.fixture()
def scene_dir(tmp_path, capsys):
    src = _scan(tmp_path / "src")
    assert _prepare(capsys, src, tmp_path / "scene")[0] == 0
    return tmp_path / "scene"


@pytest.mark.parametrize("points", [0, 1])
def test_an_init_cloud_too_small_for_a_surface_is_one_line(tmp_path, capsys, scene_dir, points):
    rng = np.random.default_rng(0)
    write_ply(tmp_path / "init" / "points.ply",
              PointCloud(rng.normal(size=(points, 3)), np.full((points, 3), 0.5), np.tile([0.0, 0, 1], (points, 1)),
                         np.ones(points)))
    rc, err = _gcgs(capsys, "optimize", "--scene", scene_dir, "--init-dir", tmp_path / "init", "--priors-dir",
                    tmp_path / "none", "--out-dir", tmp_path / "surfels", "--params", PARAMS, "--no-progress")
    line = _one_error_line(err, "optimize")
    assert rc == 1 and "points.ply" in line and ("no point" in line or "too few" in line)
    assert not (tmp_path / "surfels").exists()


def test_an_output_path_that_is_a_file_fails_before_training(tmp_path, capsys, scene_dir, monkeypatch):
    (tmp_path / "surfels").write_text("not a folder")
    (tmp_path / "timing").mkdir()
    monkeypatch.setattr("pipeline.runs.optimize.train", lambda *a, **k: pytest.fail("trained before the check"))
    for out, metrics, why in ((tmp_path / "surfels", tmp_path / "t.json", "is not a folder"),
                              (tmp_path / "s2", tmp_path / "timing", "is a folder")):
        rc, err = _gcgs(capsys, "optimize", "--scene", scene_dir, "--init-dir", tmp_path / "init", "--priors-dir",
                        tmp_path / "none", "--out-dir", out, "--metrics", metrics, "--params", PARAMS, "--no-progress")
        assert rc == 1 and why in _one_error_line(err, "optimize")
    assert (tmp_path / "surfels").read_text() == "not a folder"


def test_nan_in_a_surfel_file_is_named(tmp_path, capsys, scene_dir):
    rng = np.random.default_rng(0)
    params = init_params(rng.normal(scale=0.2, size=(64, 3)), None, np.full((64, 3), 0.5), 0, 0.5, rng)
    with torch.no_grad():
        params.means[3, 1] = float("nan")
    (tmp_path / "surfels").mkdir()
    write_surfel_ply(tmp_path / "surfels" / "surfels.ply", params, np.diag([100.0, 100.0, 100.0, 1.0]))
    rc, err = _gcgs(capsys, "mesh", "--scene", scene_dir, "--surfels-dir", tmp_path / "surfels", "--out-dir",
                    tmp_path / "mesh", "--init-dir", tmp_path / "init", "--params", PARAMS)
    line = _one_error_line(err, "mesh")
    assert rc == 1 and "surfels.ply: 1 surfel(s) hold NaN" in line and "surfel 3" in line
    assert not (tmp_path / "mesh").exists()
    # Good surfels, but an init folder without depth maps, or none: one line each, no mesh.
    with torch.no_grad():
        params.means[3, 1] = 0.0
    write_surfel_ply(tmp_path / "surfels" / "surfels.ply", params, np.diag([100.0, 100.0, 100.0, 1.0]))
    rc, err = _gcgs(capsys, "mesh", "--scene", scene_dir, "--surfels-dir", tmp_path / "surfels", "--out-dir",
                    tmp_path / "mesh", "--init-dir", tmp_path / "init", "--params", PARAMS)
    line = _one_error_line(err, "mesh")
    assert rc == 1 and "missing depth map" in line and str(tmp_path / "init") in line
    rc, err = _gcgs(capsys, "mesh", "--scene", scene_dir, "--surfels-dir", tmp_path / "surfels", "--out-dir",
                    tmp_path / "mesh", "--params", PARAMS)
    assert rc == 1 and "--init-dir" in _one_error_line(err, "mesh")
    assert not (tmp_path / "mesh").exists()


def test_evaluate_out_naming_a_folder_is_one_line(tmp_path, capsys):
    (tmp_path / "out").mkdir()
    rc, err = _gcgs(capsys, "evaluate", "--mesh", tmp_path / "m.ply", "--scene", tmp_path, "--out", tmp_path / "out",
                    "--params", PARAMS)
    assert rc == 1 and "is a folder" in _one_error_line(err, "evaluate")


def test_optimize_side_files_default_beside_the_output():
    a, b = default_side_paths("data/a/scan"), default_side_paths("data/b/scan")
    assert set(a) == {"checkpoint", "metrics", "live_dir"}
    for key in a:
        assert a[key] != b[key] and a[key].parent == Path("data/a") and b[key].parent == Path("data/b")


def test_a_failed_synth_leaves_nothing_behind(tmp_path, monkeypatch):
    from pipeline.synth import scenes

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(scenes, "write_ground_truth", interrupted, raising=False)
    monkeypatch.setattr("pipeline.evaluation.gt.write_ground_truth", interrupted)
    with pytest.raises(KeyboardInterrupt):
        scenes.write_synth_scene("synth_relief", tmp_path / "out" / "synth_relief", width=40, height=30,
                                 cameras_dir=REPO / "data" / "raw" / "dtu" / "scan24", log=None)
    assert list((tmp_path / "out").iterdir()) == []
