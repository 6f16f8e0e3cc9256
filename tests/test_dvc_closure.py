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

import importlib.util
from pathlib import Path

import pytest
import yaml

_spec = importlib.util.spec_from_file_location(
    "code_closure", Path(__file__).resolve().parents[1] / "scripts" / "code_closure.py")
code_closure = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(code_closure)
REPO, SRC = code_closure.REPO, code_closure.SRC
import_closure, stage_commands, uncovered = code_closure.import_closure, code_closure.stage_commands, code_closure.uncovered
imported_files, module_file = code_closure.imported_files, code_closure.module_file


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
READS_INIT_OUTPUTS = ("priors", "optimize", "mesh", "score", "renders", "variant-train", "variant-score")


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


# Stages after the training read the trained surfels through pipeline.surfels (the model and
# its PLY files), below the trainer: the trainer's code (the optimize package, the loss
# terms) is not theirs, so an edit there (a docstring) reruns only the training stages, and
# these only when the surfels it writes change.
AFTER_TRAINING = ("mesh", "score", "variant-score", "renders")
TRAINER_CODE = ("src/pipeline/optimize", "src/pipeline/losses")


def _touches(path: str, code: str) -> bool:
    """``path`` is ``code``, lies under it, or is a folder holding it."""
    a, b = Path(path.rstrip("/")), Path(code)
    return a == b or b in a.parents or a in b.parents


@pytest.mark.parametrize("stage", AFTER_TRAINING)
def test_trainer_code_is_not_code_of_the_stages_after_it(stage):
    modules, deps = STAGES[stage]
    closure = sorted(f.relative_to(REPO).as_posix() for f in set().union(*(import_closure(m) for m in modules)))
    imported = [f for f in closure if any(_touches(f, c) for c in TRAINER_CODE)]
    assert not imported, f"stage {stage} imports the trainer's code: {imported}"
    listed = [d for d in deps if "${" not in d and any(_touches(d, c) for c in TRAINER_CODE)]
    assert not listed, f"dvc.yaml stage {stage} lists the trainer's code as deps: {listed}"


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
