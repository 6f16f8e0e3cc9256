"""Atomic outputs that never destroy what gcgs did not write (pipeline.atomic)."""
import hashlib
import json
import os
import subprocess
import sys
import tempfile

import pytest

from pipeline import atomic
from pipeline.atomic import MARKER, PARTIAL, atomic_dir, atomic_file, write_text
from pipeline.errors import OutputError


def tree_digest(root) -> dict:
    """Every file under ``root`` (relative path -> sha256): a folder's bytes, to compare."""
    out = {}
    for dirpath, _, files in os.walk(root):
        for f in files:
            p = os.path.join(dirpath, f)
            out[os.path.relpath(p, root)] = hashlib.sha256(open(p, "rb").read()).hexdigest()
    return out


def _user_folder(path):
    path.mkdir(parents=True)
    (path / "thesis.tex").write_text("years of work")
    (path / "sub").mkdir()
    (path / "sub" / "photo.png").write_bytes(b"\x89PNG data")
    return tree_digest(path)


def test_atomic_file_replaces_only_on_success(tmp_path):
    target = tmp_path / "sub" / "out.json"
    write_text(target, "one")
    with pytest.raises(RuntimeError):
        with atomic_file(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "one"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.json"]


def test_atomic_dir_replaces_only_on_success(tmp_path):
    out = tmp_path / "stage"
    with atomic_dir(out, "test") as tmp:
        (tmp / "a.txt").write_text("a")
    assert (out / "a.txt").read_text() == "a"
    assert json.loads((out / MARKER).read_text()) == {"written_by": "gcgs", "kind": "test"}
    with atomic_dir(out, "test") as tmp:  # its own output is replaced
        (tmp / "b.txt").write_text("b")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "b.txt"]
    with pytest.raises(ValueError):
        with atomic_dir(out, "test") as tmp:
            (tmp / "c.txt").write_text("c")
            raise ValueError("bad input")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stage"]  # no temporary, no lock left
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "b.txt"]


def test_a_folder_gcgs_did_not_write_is_never_replaced(tmp_path):
    user = tmp_path / "mine"
    before = _user_folder(user)
    with pytest.raises(OutputError, match="not written by gcgs"):
        with atomic_dir(user, "scene") as tmp:
            (tmp / "x").write_text("x")
    assert tree_digest(user) == before


def test_an_empty_folder_is_used(tmp_path):
    (tmp_path / "empty").mkdir()
    with atomic_dir(tmp_path / "empty", "scene") as tmp:
        (tmp / "x").write_text("x")
    assert (tmp_path / "empty" / "x").read_text() == "x"


def test_another_kind_of_gcgs_output_is_not_replaced(tmp_path):
    scene = tmp_path / "scene"
    with atomic_dir(scene, "scene") as tmp:
        (tmp / "image.png").write_bytes(b"pixels")
    before = tree_digest(scene)
    with pytest.raises(OutputError, match="holds a gcgs scene output, not a init output"):
        with atomic_dir(scene, "init"):
            pass
    assert tree_digest(scene) == before


@pytest.mark.parametrize("where", ["same", "inside", "around"])
def test_an_output_on_an_input_is_refused_before_any_work(tmp_path, where):
    src = tmp_path / "data" / "src"
    before = _user_folder(src)
    out = {"same": src, "inside": src / "out", "around": tmp_path / "data"}[where]
    ran = []
    with pytest.raises(OutputError, match="input"):
        with atomic_dir(out, "scene", inputs=(src,)):
            ran.append(True)
    assert not ran and tree_digest(src) == before


def test_the_current_folder_and_its_parents_are_refused(tmp_path, monkeypatch):
    work = tmp_path / "work"
    before = _user_folder(work)
    monkeypatch.chdir(work)
    for out in (".", "..", str(work)):
        with pytest.raises(OutputError, match="current folder"):
            with atomic_dir(out, "scene"):
                pass
    assert tree_digest(work) == before


def test_an_existing_file_is_refused(tmp_path):
    f = tmp_path / "out"
    f.write_text("keep")
    with pytest.raises(OutputError, match="not a folder"):
        with atomic_dir(f, "scene"):
            pass
    assert f.read_text() == "keep"
    (tmp_path / "dir").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        with atomic_file(tmp_path / "dir"):
            pass
    with pytest.raises(OutputError, match="is the input"):
        atomic.check_output_file(f, inputs=(f,))


def test_a_second_writer_is_refused_while_the_first_writes(tmp_path):
    out = tmp_path / "out"
    with atomic_dir(out, "scene") as tmp:
        (tmp / "first").write_text("1")
        with pytest.raises(OutputError, match="another gcgs process is writing"):
            with atomic_dir(out, "scene"):
                pass
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "first"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_second_process_is_refused(tmp_path):
    out = tmp_path / "out"
    code = ("import sys, time; from pipeline.atomic import atomic_dir\n"
            "with atomic_dir(sys.argv[1], 'scene') as t:\n"
            "    print('holding', flush=True); time.sleep(30)\n")
    child = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "holding"
        with pytest.raises(OutputError, match="another gcgs process"):
            with atomic_dir(out, "scene"):
                pass
    finally:
        child.kill()
        child.wait()
    with atomic_dir(out, "scene") as tmp:  # a killed holder's lock is gone with it
        (tmp / "x").write_text("x")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # its temporary folder cleaned up


def test_a_writer_killed_mid_write_keeps_the_old_output(tmp_path):
    out = tmp_path / "out"
    with atomic_dir(out, "scene") as tmp:
        (tmp / "old").write_text("old")
    before = tree_digest(out)
    code = ("import os, signal, sys; from pipeline.atomic import atomic_dir\n"
            "with atomic_dir(sys.argv[1], 'scene') as t:\n"
            "    (t / 'half').write_text('half'); os.kill(os.getpid(), signal.SIGKILL)\n")
    assert subprocess.run([sys.executable, "-c", code, str(out)]).returncode == -9
    assert tree_digest(out) == before
    assert any(p.name.startswith(".out.tmp-") for p in tmp_path.iterdir())  # what the kill left
    with atomic_dir(out, "scene") as tmp:
        (tmp / "new").write_text("new")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "new"]


def test_without_an_atomic_exchange_a_kill_between_renames_is_recovered(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    out = tmp_path / "out"
    with atomic_dir(out, "scene") as tmp:
        (tmp / "v1").write_text("1")
    with atomic_dir(out, "scene") as tmp:  # the rename-aside path
        (tmp / "v2").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "v2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # A kill after the old output was renamed aside and before the new one moved in:
    aside = tmp_path / ".out.old-abc"
    os.replace(out, aside)
    with pytest.raises(RuntimeError):
        with atomic_dir(out, "scene"):
            raise RuntimeError("this run fails too")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "v2"]  # the old output is back
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_the_exchange_swaps_folders(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    b.mkdir()
    (a / "in_a").write_text("")
    if not atomic._exchange(a, b):
        pytest.skip("no renameat2 RENAME_EXCHANGE on this system")
    assert [p.name for p in b.iterdir()] == ["in_a"] and not list(a.iterdir())


def test_leftover_temporaries_of_other_outputs_are_kept(tmp_path):
    out = tmp_path / "out"
    mine = tmp_path / ".out.tmp-x"
    mine.mkdir()
    (mine / PARTIAL).touch()
    theirs = tmp_path / ".out.tmp-user"  # same name pattern, not a gcgs temporary
    theirs.mkdir()
    (theirs / "notes").write_text("keep")
    with atomic_dir(out, "scene"):
        pass
    assert not mine.exists() and (theirs / "notes").read_text() == "keep"


def test_an_unwritable_place_is_one_error_naming_it(tmp_path, monkeypatch):
    def refuse(*a, **k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    # refused by the check before any work, naming the folder that cannot be written
    with pytest.raises(OutputError, match=f"cannot write the output in {tmp_path} .Permission denied"):
        with atomic_dir(tmp_path / "out", "scene"):
            pass
    with pytest.raises(OutputError, match="cannot write the output in"):
        write_text(tmp_path / "f.json", "{}")
