"""Reading the JSON files the pipeline writes (metrics, timings, reports) for the scoring
and the tables: one place that names a missing or malformed file."""
from __future__ import annotations

import json
from pathlib import Path

from pipeline.errors import InputError, MissingInputError


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
