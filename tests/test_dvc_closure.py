"""dvc.yaml lists every file of src/pipeline that a stage's command imports.

For each stage (``foreach`` stages by their template), the module its ``gcgs`` subcommand
runs (``pipeline.cli.COMMANDS``) is followed through its imports statically: every
``import``/``from ... import`` anywhere in a module (function-level ones included), a
package import pulling its ``__init__.py``, and dotted module names written as strings
(``importlib.import_module`` registries such as ``pipeline.init.backends.BACKEND_MODULES``). A
file is covered when dvc.yaml's deps of that stage list it or a folder holding it. An
edit to an uncovered file would leave outputs that ``dvc repro`` calls up to date.
"""
from __future__ import annotations

import ast
import re
import shlex
from pathlib import Path

import pytest
import yaml

from pipeline.cli import COMMANDS

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / "src"
MODULE_NAME = re.compile(r"^pipeline(\.[A-Za-z_]\w*)+$")


def module_file(name: str, src: Path = SRC) -> Path | None:
    """The file of module ``name`` under ``src`` (a package's ``__init__.py``), or None."""
    base = src.joinpath(*name.split("."))
    for f in (base.with_suffix(".py"), base / "__init__.py"):
        if f.is_file():
            return f
    return None


def _with_parents(name: str, src: Path) -> set[Path]:
    """Importing ``a.b.c`` runs ``a/__init__.py``, ``a/b/__init__.py`` and ``a/b/c``."""
    parts = name.split(".")
    files = {module_file(".".join(parts[:i]), src) for i in range(1, len(parts) + 1)}
    return {f for f in files if f is not None}


def imported_files(path: Path, src: Path = SRC) -> set[Path]:
    """Files under ``src/pipeline`` that importing the module at ``path`` runs directly."""
    rel = path.relative_to(src).with_suffix("")
    package = list(rel.parts[:-1])  # the package relative imports start from (also for __init__.py)
    found: set[Path] = set()

    def add(name: str, *, names: tuple[str, ...] = ()) -> None:
        if not (name == "pipeline" or name.startswith("pipeline.")):
            return
        found.update(_with_parents(name, src))
        for n in names:  # ``from pkg import sub`` imports the submodule sub
            f = module_file(f"{name}.{n}", src)
            if f is not None:
                found.update(_with_parents(f"{name}.{n}", src))

    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            add(name, names=tuple(a.name for a in node.names))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and MODULE_NAME.match(node.value):
            if module_file(node.value, src) is not None:  # a module named in a string: a dynamic import
                add(node.value)
    return found


def import_closure(module: str, src: Path = SRC) -> set[Path]:
    """Every file under ``src/pipeline`` that importing ``module`` can run."""
    todo = list(_with_parents(module, src))
    seen: set[Path] = set()
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        todo.extend(imported_files(f, src) - seen)
    return seen


def stage_commands(dvc_yaml: Path) -> dict[str, tuple[list[str], list[str]]]:
    """stage name -> (modules its command runs, its deps), ``foreach`` stages by their template."""
    stages = yaml.safe_load(dvc_yaml.read_text())["stages"]
    out = {}
    for name, stage in stages.items():
        body = stage.get("do", stage)
        cmds = body["cmd"] if isinstance(body["cmd"], list) else [body["cmd"]]
        modules = []
        for cmd in cmds:
            words = shlex.split(cmd)
            for i, w in enumerate(words[:-1]):
                if w == "gcgs":
                    sub = words[i + 1]
                    assert sub in COMMANDS, f"stage {name}: `gcgs {sub}` is not a gcgs subcommand"
                    modules.append(COMMANDS[sub][0])
                elif w == "-m" and words[i + 1].startswith("pipeline"):
                    modules.append(words[i + 1])
        deps = [d if isinstance(d, str) else next(iter(d)) for d in body.get("deps", [])]
        out[name] = (modules, deps)
    return out


def uncovered(files: set[Path], deps: list[str], repo: Path = REPO) -> list[str]:
    """Files (repository-relative) that no dep names, itself or as a folder holding it."""
    covered = [Path(d.rstrip("/")) for d in deps if "${" not in d]
    rel = sorted(f.relative_to(repo).as_posix() for f in files)
    return [f for f in rel if not any(Path(f) == c or c in Path(f).parents for c in covered)]


STAGES = stage_commands(REPO / "dvc.yaml")


def test_every_stage_runs_a_pipeline_module():
    for name, (modules, _) in STAGES.items():
        assert modules, f"stage {name}: no `gcgs SUBCOMMAND` or `python -m pipeline...` in its cmd"


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_stage_deps_cover_the_code_it_imports(stage):
    modules, deps = STAGES[stage]
    repeated = sorted({d for d in deps if deps.count(d) > 1})
    assert not repeated, f"dvc.yaml stage {stage} lists deps twice: {repeated}"
    closure = set().union(*(import_closure(m) for m in modules))
    missing = uncovered(closure, deps)
    assert not missing, f"dvc.yaml stage {stage} does not list code its command imports: {missing}"



# Stages that read the init's files but never run a backend: an edit to a backend or to the
# init's settings must not make their code stale (it reruns them only through the init's
# outputs, when those change).
READS_INIT_OUTPUTS = ("priors", "optimize", "mesh", "evaluate", "renders", "variant-train", "variant-score")


@pytest.mark.parametrize("stage", READS_INIT_OUTPUTS)
def test_init_backends_are_not_code_of_the_stages_after_it(stage):
    modules, _ = STAGES[stage]
    closure = {f.relative_to(SRC).as_posix() for f in set().union(*(import_closure(m) for m in modules))}
    init_code = sorted(f for f in closure if f.startswith("pipeline/init/") or f.startswith("pipeline/config/"))
    allowed = {"pipeline/init/__init__.py", "pipeline/init/io.py", "pipeline/config/__init__.py",
               "pipeline/config/params.py", "pipeline/config/data.py", "pipeline/config/evaluate.py",
               "pipeline/config/loss.py", "pipeline/config/mesh.py", "pipeline/config/optimize.py",
               "pipeline/config/priors.py", "pipeline/config/ablation.py", "pipeline/config/scenes.py",
               "pipeline/config/variants.py"}
    assert set(init_code) <= allowed, f"stage {stage} imports init code or settings: {sorted(set(init_code) - allowed)}"

# The checker itself, on a small package written here.
def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)


def test_closure_follows_every_kind_of_import(tmp_path):
    _write(tmp_path, {
        "pipeline/__init__.py": "",
        "pipeline/stage.py": "from pipeline.lib import helper\nfrom . import rel\n"
                             "def f():\n    import pipeline.late.mod\n",
        "pipeline/lib/__init__.py": "",
        "pipeline/lib/helper.py": "import numpy\nfrom pipeline.util import x\n",
        "pipeline/util.py": "x = 1\n",
        "pipeline/rel.py": "REGISTRY = {'a': 'pipeline.dyn'}\n",
        "pipeline/dyn.py": "",
        "pipeline/late/__init__.py": "",
        "pipeline/late/mod.py": "",
        "pipeline/unused.py": "",
    })
    got = {f.relative_to(tmp_path).as_posix() for f in import_closure("pipeline.stage", tmp_path)}
    assert got == {"pipeline/__init__.py", "pipeline/stage.py", "pipeline/lib/__init__.py", "pipeline/lib/helper.py",
                   "pipeline/util.py", "pipeline/rel.py", "pipeline/dyn.py", "pipeline/late/__init__.py",
                   "pipeline/late/mod.py"}
    files = {tmp_path / p for p in got}
    assert uncovered(files, ["pipeline/lib", "pipeline/stage.py", "pipeline/late/", "${item.src}"], tmp_path) == [
        "pipeline/__init__.py", "pipeline/dyn.py", "pipeline/rel.py", "pipeline/util.py"]


def test_commands_of_a_foreach_stage_and_a_python_module(tmp_path):
    (tmp_path / "dvc.yaml").write_text(yaml.safe_dump({"stages": {
        "a": {"foreach": "${scenes}", "do": {"cmd": "gcgs init --scene ${key}", "deps": ["src/x", {"src/y": {}}]}},
        "b": {"cmd": ["python -m pipeline.stages.tsdf --out x", "echo done"]},
    }}))
    got = stage_commands(tmp_path / "dvc.yaml")
    assert got == {"a": (["pipeline.stages.init"], ["src/x", "src/y"]), "b": (["pipeline.stages.tsdf"], [])}
