"""The init backends by name: each module provides ``run(scene, cfg) -> InitResult``.

The registry lives here, not in the package's ``__init__``, so that a module reading the
init's files (:mod:`pipeline.init.io`) does not import every backend: a stage that only
reads the init's outputs does not depend on the backends' code (dvc.yaml deps)."""
from __future__ import annotations

import importlib

BACKEND_MODULES = {
    "mvs": "pipeline.init.mvs",
    "sfm": "pipeline.init.sfm",
    "mast3r": "pipeline.init.mast3r",
    "random": "pipeline.init.random_init",
}


def run_backend(name: str, scene, cfg):
    """Run backend ``name`` on ``scene`` with an :class:`~pipeline.config.init.InitConfig`."""
    if name not in BACKEND_MODULES:
        raise ValueError(f"unknown init backend {name!r} (have {', '.join(BACKEND_MODULES)})")
    return importlib.import_module(BACKEND_MODULES[name]).run(scene, cfg)


def match_summary(info: dict) -> list[str]:
    """Lines for the console: per-view matched and consistent fractions of the mask
    pixels (depth backends that report them); the warnings in ``info`` go to stderr apart
    (the stage prints them with :func:`pipeline.errors.print_warning`)."""
    lines = []
    if "matched_fraction" in info:
        views = info.get("views") or range(len(info["matched_fraction"]))
        pairs = (f"{v}: {m:.0%}/{c:.0%}" for v, m, c in zip(views, info["matched_fraction"], info["consistent_fraction"]))
        lines.append("  matched/consistent fraction of mask pixels per view: " + ", ".join(pairs))
    return lines
