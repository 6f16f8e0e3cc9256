"""The code a dvc.yaml stage runs: every file of src/pipeline that its command imports.

For each stage (``foreach`` stages by their template), the module its ``gcgs`` subcommand
runs (``pipeline.cli.COMMANDS``) is followed through its imports statically: every
``import``/``from ... import`` anywhere in a module (function-level ones included), a
package import pulling its ``__init__.py``, and dotted module names written as strings
(``importlib.import_module`` registries such as ``pipeline.init.backends.BACKEND_MODULES``).
Used by scripts/dvc_code_deps.py (which rewrites dvc.yaml's code deps) and by
tests/test_dvc_closure.py (which checks them).
"""
from __future__ import annotations

import ast
import re
import shlex
from pathlib import Path

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
