import pytest

from pipeline.atomic import atomic_dir, atomic_file, write_text


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
    with atomic_dir(out) as tmp:
        (tmp / "a.txt").write_text("a")
    assert (out / "a.txt").read_text() == "a"
    with pytest.raises(ValueError):
        with atomic_dir(out) as tmp:
            (tmp / "b.txt").write_text("b")
            raise ValueError("bad input")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stage"]
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]
