"""Reading the pipeline's reports (the per-scene metrics JSON and its kin) for the tables
and the index: one place that names a missing file or figure."""
from __future__ import annotations

import json
import math
from pathlib import Path

from pipeline.errors import InputError, MissingInputError


def covered_fraction(counts: dict, path: str | Path) -> float:
    """Fraction of the GT points (above the plane) within ``max_dist`` of the mesh, from
    :func:`pipeline.evaluation.dtu_eval.evaluate_mesh`'s ``counts``. The DTU protocol leaves
    the other GT points out of completeness, so a mesh missing a region entirely is not
    penalised for it: this fraction says how much of the object a Chamfer figure covers."""
    used, total = figure(counts, "completeness_used", path), figure(counts, "gt_above_plane", path)
    if total <= 0:
        raise ReportError(f"{path}: `gt_above_plane` must be positive, got {total}")
    return used / total


class ReportError(InputError):
    """A report or data file that cannot be read or lacks a figure; names the file."""


def read_json(path: str | Path, what: str, made_by: str = "") -> dict:
    """A JSON object from ``path``; missing or malformed files raise naming the file
    (and, when missing, ``made_by``: what writes it)."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: no {what} (file not found{'; ' + made_by if made_by else ''})")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ReportError(f"{path}: {what} is not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise ReportError(f"{path}: {what} must be a JSON object, got {type(data).__name__}")
    return data


def figure(data: dict, keys: str, path: str | Path) -> float:
    """The finite number at dotted ``keys`` of ``data`` (read from ``path``)."""
    value = data
    for k in keys.split("."):
        if not isinstance(value, dict) or k not in value:
            raise ReportError(f"{path}: missing `{keys}`")
        value = value[k]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ReportError(f"{path}: `{keys}` must be a finite number, got {value!r}")
    return float(value)


