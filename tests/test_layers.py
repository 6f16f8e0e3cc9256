"""The packages of src/pipeline import downwards only (README: "Where the code lives"): a
module imports its own package or packages of a lower layer, never a higher one, so a
change low in the stack is the only kind that reruns much of the DAG."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "src" / "pipeline"

# Lowest first; a package may import from any earlier layer.
LAYERS = [
    {"errors", "npz", "measure", "losses"},
    {"threads", "heap"},
    {"config", "geometry", "atomic", "jsonfile", "onnx_models", "rasterizer"},
    {"ply", "curves", "raycast"},
    {"surfels"},
    {"data"},
    {"init", "priors"},
    {"optimize"},
    {"meshing"},
    {"labelling"},
    {"masks"},
    {"evaluation"},
    {"synth"},
    {"runs", "reports", "sweep", "cli"},
    {"stages", "benchmarks"},
]
RANK = {name: i for i, layer in enumerate(LAYERS) for name in layer}


def _unit(module: str) -> str | None:
    """``pipeline.X[.Y]`` -> ``X`` (a package or a top-level module)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "pipeline" else None


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module == "pipeline":
                yield from (f"pipeline.{a.name}" for a in node.names)
            else:
                yield node.module
        elif isinstance(node, ast.Import):
            yield from (a.name for a in node.names)


def test_every_unit_has_a_layer():
    units = {p.stem if p.is_file() else p.name for p in ROOT.iterdir()
             if (p.suffix == ".py" and p.stem != "__init__") or (p.is_dir() and (p / "__init__.py").is_file())}
    assert units == set(RANK), f"give these a layer: {sorted(units - set(RANK))}; gone: {sorted(set(RANK) - units)}"


def test_no_module_imports_upwards():
    upward = []
    for path in sorted(ROOT.rglob("*.py")):
        me = _unit("pipeline." + ".".join(path.relative_to(ROOT).with_suffix("").parts))
        for module in _imports(path):
            target = _unit(module)
            if target is None or target == me or me is None:
                continue
            if RANK[target] >= RANK[me]:
                upward.append(f"{path.relative_to(ROOT)} imports {module} (layer {RANK[target]} >= {RANK[me]})")
    assert not upward, "\n".join(upward)
