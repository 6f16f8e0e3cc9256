"""Side doors (issue 57): the options that write single files or side folders (checkpoint,
timing metrics, curves, ``--out``, ``--report``) are guarded like output folders, as a user
runs the commands: refused in one line before any work when they are an input, inside an
input folder, or an existing file gcgs did not write; a checkpoint is deleted only if it is
one of ours; the curves never clean a folder; a rerun keeps what a user added to its
earlier output; unwritable places and mount points fail before training; a resumed run
keeps the whole curve. Every file outside the named output is compared byte for byte."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest

from optimize_scene import interrupt_training_at, write_stage_inputs
from pipeline import atomic, cli
from pipeline.curves import CurveLog
from pipeline.errors import OutputError
from test_atomic import tree_digest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """A tiny scene, init cloud and priors written to disk, and params for a 10-iteration run."""
    return write_stage_inputs(tmp_path_factory.mktemp("side"))


def _optimize(root: Path, priors: Path, out: Path, **side: Path) -> int:
    argv = ["optimize", "--scene", root / "scene", "--init-dir", root / "init", "--priors-dir", priors,
            "--out-dir", out, "--no-progress", "--params", root / "params.yaml"]
    for flag, path in side.items():
        argv += [f"--{flag.replace('_', '-')}", path]
    return cli.main([str(a) for a in argv])


def _one_error(capsys, command: str) -> str:
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"gcgs {command}: error: "), lines
    return lines[0]


def _inputs_digest(root: Path, priors: Path) -> dict:
    return {"scene": tree_digest(root / "scene"), "init": tree_digest(root / "init"), "priors": tree_digest(priors)}


def _no_training(monkeypatch):
    """Make the work fail loudly if it starts: a refusal must come before the inputs are loaded."""
    from pipeline.runs import optimize as run_module

    def forbidden(*a, **k):
        raise AssertionError("the work started before the refusal")

    monkeypatch.setattr(run_module, "load_training_inputs", forbidden)


# -- checkpoints ------------------------------------------------------------------------------

@pytest.mark.parametrize("case", ["user_file", "scene_camera_file", "init_cloud", "folder"])
def test_a_checkpoint_path_that_is_not_ours_is_refused_before_training(inputs, tmp_path, capsys, monkeypatch, case):
    root, priors = inputs
    before = _inputs_digest(root, priors)
    notes = tmp_path / "mynotes.txt"
    notes.write_text("a week of notes")
    ckpt = {"user_file": notes, "scene_camera_file": root / "scene" / "cameras_sphere.npz",
            "init_cloud": root / "init" / "points.ply", "folder": tmp_path}[case]
    _no_training(monkeypatch)
    assert _optimize(root, priors, tmp_path / "out", checkpoint=ckpt) == 1
    message = _one_error(capsys, "optimize")
    assert str(ckpt) in message
    expected = {"user_file": "not written by gcgs", "scene_camera_file": "inside the input folder",
                "init_cloud": "inside the input folder", "folder": "is a folder"}[case]
    assert expected in message
    assert notes.read_text() == "a week of notes" and _inputs_digest(root, priors) == before
    assert not (tmp_path / "out").exists()


def test_only_a_gcgs_checkpoint_is_deleted_when_the_run_ends(inputs, tmp_path, capsys):
    root, priors = inputs
    ckpt = tmp_path / "run.pt"
    assert _optimize(root, priors, tmp_path / "out", checkpoint=ckpt) == 0
    assert not ckpt.exists()  # ours, and finished: deleted
    # an empty file in its place (nothing to lose) is taken, then replaced by a checkpoint of ours
    ckpt.touch()
    assert _optimize(root, priors, tmp_path / "out2", checkpoint=ckpt) == 0
    assert not ckpt.exists()


def test_a_gcgs_file_of_another_kind_is_not_taken_for_a_checkpoint(inputs, tmp_path, capsys):
    root, priors = inputs
    metrics = tmp_path / "timing.json"
    assert _optimize(root, priors, tmp_path / "out", metrics=metrics, checkpoint=tmp_path / "a.pt") == 0
    before = metrics.read_bytes()
    assert _optimize(root, priors, tmp_path / "out2", checkpoint=metrics) == 1
    assert "not a checkpoint" in _one_error(capsys, "optimize")
    assert metrics.read_bytes() == before


# -- file outputs inside inputs, or a user's files --------------------------------------------

@pytest.mark.parametrize("where", ["scene/scene.json", "init/init.json", "scene/image/new.json"])
def test_optimize_metrics_inside_an_input_folder_is_refused(inputs, tmp_path, capsys, monkeypatch, where):
    root, priors = inputs
    before = _inputs_digest(root, priors)
    _no_training(monkeypatch)
    assert _optimize(root, priors, tmp_path / "out", metrics=root / where) == 1
    assert "input" in _one_error(capsys, "optimize")
    assert _inputs_digest(root, priors) == before and not (root / "scene" / "image" / "new.json").exists()


def test_a_user_file_as_metrics_is_refused_and_our_own_is_replaced(inputs, tmp_path, capsys, monkeypatch):
    root, priors = inputs
    mine = tmp_path / "results.json"
    mine.write_text('{"my": "numbers"}')
    assert _optimize(root, priors, tmp_path / "out", metrics=mine, checkpoint=tmp_path / "c.pt") == 1
    assert "not written by gcgs" in _one_error(capsys, "optimize")
    assert mine.read_text() == '{"my": "numbers"}'
    ours = tmp_path / "timing.json"
    assert _optimize(root, priors, tmp_path / "out", metrics=ours, checkpoint=tmp_path / "c.pt") == 0
    assert _optimize(root, priors, tmp_path / "out", metrics=ours, checkpoint=tmp_path / "c.pt") == 0  # rerun: ours
    assert atomic.written_kind(ours) == "file"


def test_file_outputs_of_the_other_commands_inside_their_inputs_are_refused(inputs, tmp_path, capsys):
    root, priors = inputs
    before = _inputs_digest(root, priors)
    mesh_dir = tmp_path / "mesh"
    mesh_dir.mkdir()
    (mesh_dir / "mesh.json").write_text("{}")
    cases = [
        ("tsdf", ["tsdf", "--init-dir", root / "init", "--scene", root / "scene", "--out", root / "init" / "points.ply"]),
        ("tsdf", ["tsdf", "--init-dir", root / "init", "--scene", root / "scene",
                  "--out", root / "scene" / "cameras_sphere.npz"]),
        ("init", ["init", "--scene", root / "scene", "--out-dir", tmp_path / "i", "--metrics", root / "scene" / "x.json",
                  "--params", root / "params.yaml"]),
        ("score", ["score", "tiny", "--scene", root / "scene", "--surfels-dir", tmp_path / "s", "--mesh-dir", mesh_dir,
                   "--train-timing", tmp_path / "t.json", "--out", mesh_dir / "mesh.json", "--params", root / "params.yaml"]),
        ("evaluate", ["evaluate", "--mesh", tmp_path / "m.ply", "--scene", root / "scene", "--out", root / "scene" / "scene.json",
                      "--params", root / "params.yaml"]),
        ("limit", ["limit", "tiny", "--synth-dir", tmp_path / "synth", "--scene", root / "scene", "--out-dir",
                   tmp_path / "l", "--report", root / "scene" / "scene.json", "--params", root / "params.yaml"]),
    ]
    for command, argv in cases:
        assert cli.main([str(a) for a in argv]) == 1, argv
        assert "input" in _one_error(capsys, command)
    assert _inputs_digest(root, priors) == before and (mesh_dir / "mesh.json").read_text() == "{}"


def test_check_output_file_rules(tmp_path):
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "a.ply").write_text("x")
    with pytest.raises(OutputError, match="is the input"):
        atomic.check_output_file(folder / "a.ply", inputs=(folder / "a.ply",))
    with pytest.raises(OutputError, match="inside the input folder"):
        atomic.check_output_file(folder / "sub" / "b.json", inputs=(folder,))
    with pytest.raises(OutputError, match="not written by gcgs"):
        atomic.check_output_file(folder / "a.ply")
    (tmp_path / "empty.json").touch()
    atomic.check_output_file(tmp_path / "empty.json")  # nothing to lose
    with pytest.raises(OutputError, match="is a file, not a folder"):
        atomic.check_output_file(folder / "a.ply" / "x.json")
    atomic.write_text(tmp_path / "ours.json", "{}")
    assert atomic.written_kind(tmp_path / "ours.json") == "file"
    atomic.write_text(tmp_path / "ours.json", "[]")  # ours: replaced


# -- the curves folder ----------------------------------------------------------------------

def _pipeline_files(folder: Path) -> None:
    """What a DVC project's root holds that DVCLive's clean-up deleted."""
    (folder / "dvc.yaml").write_text("stages: {}\n")
    (folder / "params.yaml").write_text("a: 1\n")
    (folder / "report.md").write_text("# mine\n")
    for sub in ("metrics", "images", "sklearn", "custom"):
        (folder / "plots" / sub).mkdir(parents=True)
        (folder / "plots" / sub / "mine.tsv").write_text("x\n")


def test_the_curves_never_clean_a_folder(inputs, tmp_path, capsys):
    root, priors = inputs
    live = tmp_path / "project"
    live.mkdir()
    _pipeline_files(live)
    before = tree_digest(live)
    assert _optimize(root, priors, tmp_path / "out", live_dir=live, checkpoint=tmp_path / "c.pt") == 0
    after = tree_digest(live)
    assert {k: v for k, v in after.items() if k in before} == before  # nothing of the user's changed
    added = sorted(set(after) - set(before))
    assert "metrics.json" in added and all(a == "metrics.json" or a.startswith("plots/metrics/train/") for a in added)


@pytest.mark.parametrize("bad", ["summary", "curve", "file"])
def test_a_curves_folder_with_foreign_files_of_its_names_is_refused(inputs, tmp_path, capsys, monkeypatch, bad):
    root, priors = inputs
    live = tmp_path / "live"
    if bad == "file":
        live.write_text("not a folder")
    elif bad == "summary":
        live.mkdir()
        (live / "metrics.json").write_text('{"accuracy": 0.9}')
    else:
        (live / "plots" / "metrics" / "train").mkdir(parents=True)
        (live / "plots" / "metrics" / "train" / "total.tsv").write_text("epoch,loss\n1,2\n")
    before = tree_digest(tmp_path) if live.is_dir() else live.read_text()
    _no_training(monkeypatch)
    assert _optimize(root, priors, tmp_path / "out", live_dir=live, checkpoint=tmp_path / "c.pt") == 1
    _one_error(capsys, "optimize")
    assert (tree_digest(tmp_path) if live.is_dir() else live.read_text()) == before


def test_the_curves_match_dvclive_byte_for_byte(tmp_path):
    """The format DVC plots read: the reference is DVCLive itself, fed the same rows."""
    from dvclive import Live

    rows = [{"iteration": 0, "total": 0.5, "l1": 0.25}, {"iteration": 10, "total": 0.125, "l1": 1 / 3, "mv": 2.0},
            {"iteration": 20, "total": float("nan"), "l1": 0.1, "mv": 1.5, "surfels": 123}]
    terms = ("total", "l1", "mv", "surfels")
    ours = CurveLog(tmp_path / "ours", "train", terms)
    live = Live(str(tmp_path / "theirs"), save_dvc_exp=False, dvcyaml=None, report=None)
    for row in rows:
        ours.log(row["iteration"], row)
        live.step = row["iteration"]
        for k in terms:
            if k in row:
                live.log_metric(f"train/{k}", row[k], plot=True)
    ours.end()
    live.end()
    theirs = {k: v for k, v in tree_digest(tmp_path / "theirs").items() if k.endswith((".tsv", "metrics.json"))}
    assert tree_digest(tmp_path / "ours") == theirs


def test_a_resumed_run_keeps_the_whole_curve(inputs, tmp_path, capsys, monkeypatch):
    root, priors = inputs
    resume = interrupt_training_at(monkeypatch, 6)
    side = {"checkpoint": tmp_path / "c.pt", "live_dir": tmp_path / "live", "metrics": tmp_path / "t.json"}
    assert _optimize(root, priors, tmp_path / "out", **side) == 130
    resume()
    assert _optimize(root, priors, tmp_path / "out", **side) == 0
    whole = {"checkpoint": tmp_path / "c2.pt", "live_dir": tmp_path / "live2", "metrics": tmp_path / "t2.json"}
    assert _optimize(root, priors, tmp_path / "out2", **whole) == 0
    def curves(live: Path) -> dict:  # every curve but the wall-clock one, and the steps of all
        return {p.name: p.read_text() if p.stem != "seconds" else [ln.split("\t")[0] for ln in p.read_text().splitlines()]
                for p in sorted((live / "plots/metrics/train").iterdir())}

    resumed, uninterrupted = curves(tmp_path / "live"), curves(tmp_path / "live2")
    assert resumed == uninterrupted and "total.tsv" in resumed and "surfels.tsv" in resumed
    steps = [ln.split("\t")[0] for ln in resumed["total.tsv"].splitlines()]
    assert steps[:2] == ["step", "0"] and len(steps) == len(set(steps))  # from the start, no repeats


# -- folders: what a user added, mount points, unwritable places ------------------------------

def test_a_rerun_keeps_what_the_user_added_to_its_earlier_output(inputs, tmp_path, capsys):
    root, priors = inputs
    out = tmp_path / "out"
    side = {"checkpoint": tmp_path / "c.pt", "metrics": tmp_path / "t.json", "live_dir": tmp_path / "live"}
    assert _optimize(root, priors, out, **side) == 0
    capsys.readouterr()
    (out / "NOTES.md").write_text("what I saw")
    (out / "my_edits").mkdir()
    (out / "my_edits" / "cleaned.ply").write_text("ply")
    shutil.copy(out / "surfels.ply", out / "surfels_cleaned.ply")  # a copy: not marked as ours
    assert _optimize(root, priors, out, **side) == 0
    err = capsys.readouterr().err
    kept = [p for p in tmp_path.iterdir() if p.name.startswith("out.kept-")]
    assert len(kept) == 1 and "3 entries gcgs did not write were moved to" in err and str(kept[0]) in err
    assert (kept[0] / "NOTES.md").read_text() == "what I saw"
    assert (kept[0] / "my_edits" / "cleaned.ply").read_text() == "ply"
    assert (kept[0] / "surfels_cleaned.ply").is_file()
    assert not (out / "NOTES.md").exists() and (out / "surfels.ply").is_file()
    # a rerun onto an output nobody touched keeps nothing aside
    assert _optimize(root, priors, out, **side) == 0
    assert len([p for p in tmp_path.iterdir() if p.name.startswith("out.kept-")]) == 1


def test_a_mount_point_output_is_refused_before_training(inputs, tmp_path, capsys, monkeypatch):
    root, priors = inputs
    mount = tmp_path / "mnt"
    mount.mkdir()
    real = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: Path(p) == mount or real(p))
    _no_training(monkeypatch)
    assert _optimize(root, priors, mount, checkpoint=tmp_path / "c.pt") == 1
    assert "mount point" in _one_error(capsys, "optimize")


def test_an_unwritable_place_is_refused_before_training(inputs, tmp_path, capsys, monkeypatch):
    root, priors = inputs
    locked = tmp_path / "locked"
    locked.mkdir()
    real = tempfile.mkstemp

    def refuse_in_locked(*a, **k):
        if Path(k.get("dir", "")) == locked:
            raise PermissionError(13, "Permission denied")
        return real(*a, **k)

    monkeypatch.setattr(tempfile, "mkstemp", refuse_in_locked)
    _no_training(monkeypatch)
    for side in ({"metrics": locked / "t.json"}, {"checkpoint": locked / "c.pt"}, {"live_dir": locked / "live"}):
        assert _optimize(root, priors, tmp_path / "out", **{"checkpoint": tmp_path / "c.pt", **side}) == 1
        assert "cannot write the output in" in _one_error(capsys, "optimize")
    assert _optimize(root, priors, locked / "out", checkpoint=tmp_path / "c.pt") == 1
    assert "cannot write the output in" in _one_error(capsys, "optimize")
    assert list(locked.iterdir()) == []


def test_the_table_names_tests_that_exist():
    """docs/outputs.md's table of probed cases names the test of each row: it must exist."""
    import ast

    text = (REPO / "docs" / "outputs.md").read_text()
    table = text[text.index("## Cases probed"):]
    named = {ref.strip("` ") for line in table.splitlines() if line.startswith("|")
             for cell in line.split("|")[3:4] for ref in cell.split(",") if "::" in ref}
    assert len(named) >= 10
    for ref in named:
        file, name = ref.split("::")
        tree = ast.parse((REPO / "tests" / file).read_text())
        assert name in {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}, ref
