"""scripts/repro_parallel.py: the ordering (dependencies first, the heaviest chain first) and the commit."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_spec = importlib.util.spec_from_file_location(
    "repro_parallel", Path(__file__).resolve().parents[1] / "scripts" / "repro_parallel.py")
repro_parallel = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(repro_parallel)


def _brute_valid(order, deps):
    seen = set()
    for s in order:
        if not deps[s] <= seen:
            return False
        seen.add(s)
    return seen == set(deps)


def test_every_stage_comes_after_the_stages_it_needs():
    deps = {"init": set(), "train_a": {"init"}, "train_b": {"init"}, "score_a": {"train_a"},
            "score_b": {"train_b"}, "table": {"score_a", "score_b"}, "other": set()}
    order = repro_parallel.schedule_order(deps, {})
    assert _brute_valid(order, deps)


def test_the_heaviest_chain_starts_first():
    # b's chain (b -> b2, 10 + 1) outweighs a's (a -> a2, 1 + 1) and c (5): b first, then c.
    deps = {"a": set(), "a2": {"a"}, "b": set(), "b2": {"b"}, "c": set()}
    order = repro_parallel.schedule_order(deps, {"b": 10.0, "c": 5.0})
    assert order[:2] == ["b", "c"]
    assert _brute_valid(order, deps)


def test_a_cycle_is_an_error_naming_its_stages():
    with pytest.raises(ValueError, match="cycle.*'x'"):
        repro_parallel.schedule_order({"x": {"y"}, "y": {"x"}, "z": set()}, {})


def test_commit_records_the_stage_and_ignores_its_outputs(tmp_path, monkeypatch):
    """A stage the workers ran is committed as `dvc repro` would leave it: in dvc.lock with
    its output's hash, the output in .gitignore (else `git status` shows DVC's outputs)."""
    import subprocess
    import yaml

    monkeypatch.chdir(tmp_path)
    subprocess.run(["git", "init", "-q"], check=True)
    subprocess.run(["dvc", "init", "-q"], check=True)
    Path("dvc.yaml").write_text(yaml.safe_dump({"stages": {"make": {"cmd": "true", "outs": ["out/data"]}}}))
    Path("out/data").mkdir(parents=True)
    Path("out/data/a.txt").write_text("surfels\n")
    repro_parallel.commit_stages(["make"])
    lock = yaml.safe_load(Path("dvc.lock").read_text())
    assert lock["stages"]["make"]["outs"][0]["path"] == "out/data"
    assert lock["stages"]["make"]["outs"][0]["md5"].endswith(".dir")
    assert Path("out/.gitignore").read_text().split() == ["/data"]
    status = subprocess.run(["git", "status", "--porcelain", "--untracked-files=all"], capture_output=True,
                            text=True, check=True).stdout
    assert "out/data" not in status


def _tiny_repo(cmd_a: str) -> None:
    import subprocess
    import yaml

    Path("dvc.yaml").write_text(yaml.safe_dump({"stages": {
        "a": {"cmd": cmd_a, "outs": ["a.txt"]},
        "b": {"cmd": "cat a.txt > b.txt && echo ran >> b_runs.log", "deps": ["a.txt"], "outs": ["b.txt"]}}}))
    subprocess.run(["git", "init", "-q"], check=True)
    subprocess.run(["dvc", "init", "-q"], check=True)
    Path(".gitignore").write_text("b_runs.log\n")


def _run_main(monkeypatch):
    import sys

    monkeypatch.setattr(sys, "argv", ["repro_parallel.py", "--jobs", "1"])
    with pytest.raises(SystemExit) as end:
        repro_parallel.main()
    assert end.value.code == 0


@pytest.mark.parametrize("new_cmd_a, b_reruns", [("printf 'x\\n' > a.txt", False), ("echo y > a.txt", True)])
def test_a_stage_after_one_that_wrote_the_same_bytes_is_left_alone(tmp_path, monkeypatch, new_cmd_a, b_reruns):
    """As `dvc repro`: `a`'s command changed, so `a` runs; `b` runs again only if `a`'s
    output came out different from the one b's dvc.lock entry records."""
    import subprocess
    import yaml

    monkeypatch.chdir(tmp_path)
    _tiny_repo("echo x > a.txt")
    subprocess.run(["dvc", "repro", "-q"], check=True)
    assert Path("b_runs.log").read_text().count("ran") == 1
    spec = yaml.safe_load(Path("dvc.yaml").read_text())
    spec["stages"]["a"]["cmd"] = new_cmd_a
    Path("dvc.yaml").write_text(yaml.safe_dump(spec))
    _run_main(monkeypatch)
    assert Path("b_runs.log").read_text().count("ran") == (2 if b_reruns else 1)
    assert Path("b.txt").read_text() == ("y\n" if b_reruns else "x\n")
    status = subprocess.run(["dvc", "status", "-q"], capture_output=True, text=True)
    assert status.returncode == 0 and "changed" not in status.stdout, status.stdout
