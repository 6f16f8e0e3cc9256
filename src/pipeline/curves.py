"""Training curves in DVCLive's file layout, which ``dvc plots`` reads, written by gcgs alone.

``DIR/plots/metrics/GROUP/TERM.tsv`` holds one ``step<TAB>TERM`` row per logged iteration,
``DIR/metrics.json`` the last value of each term and the last step. These are the only
files the logger writes or removes: it never cleans a folder (DVCLive's start-up clean-up
deletes ``dvc.yaml``, ``params.yaml``, reports and every plot folder of the folder it is
given), and it refuses, before any work, a folder holding a file of those names that is not a
curve. A resumed run keeps the rows logged before the iteration it resumes from, so the curve
of the whole training survives an interruption.
"""
from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable
from pathlib import Path

from pipeline import atomic
from pipeline.errors import OutputError

SUMMARY = "metrics.json"


def _summary_path(folder: Path) -> Path:
    return folder / SUMMARY


def _group_dir(folder: Path, group: str) -> Path:
    return folder / "plots" / "metrics" / group


def _is_curve(path: Path) -> bool:
    """A TSV whose header is ``step<TAB>NAME`` with NAME its file stem: one of ours."""
    try:
        with open(path, encoding="utf-8") as fh:
            return fh.readline().rstrip("\n") == f"step\t{path.stem}"
    except (OSError, UnicodeDecodeError):
        return False


def _is_summary(path: Path, group: str) -> bool:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return (isinstance(data, dict) and set(data) <= {group, "step"} and isinstance(data.get(group, {}), dict)
            and isinstance(data.get("step", 0), int))


def check_curves_dir(folder: str | Path, group: str, terms: Iterable[str],
                     inputs: Iterable[str | Path | None] = ()) -> Path:
    """Refuse (:class:`OutputError`, one line) a curves folder that is an existing file, is,
    lies inside or holds an input, or holds a file the logger would replace that is not a
    curve of ours. Returns the resolved folder."""
    shown = folder
    folder = atomic.resolved_path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{shown}: curves folder path exists and is not a folder; choose another path")
    for given, where in atomic.overlapping_inputs(folder, inputs):
        raise OutputError(f"{shown}: curves folder {where} the input {given}; choose another folder")
    summary = _summary_path(folder)
    if summary.exists() and not (summary.is_file() and _is_summary(summary, group)):
        raise OutputError(f"{summary}: exists and is not a gcgs curves summary; refusing to overwrite it: "
                          "choose another curves folder")
    for term in terms:
        tsv = _group_dir(folder, group) / f"{term}.tsv"
        if tsv.exists() and not (tsv.is_file() and _is_curve(tsv)):
            raise OutputError(f"{tsv}: exists and is not a gcgs curve; refusing to overwrite it: "
                              "choose another curves folder")
    atomic.check_creatable(summary, shown)
    return folder


class CurveLog:
    """Appends logged rows to the curve files of ``folder`` (checked by
    :func:`check_curves_dir` first). The first row's step decides what is kept: rows of
    earlier runs at that step or later are dropped (all of them for a fresh run, which starts
    at step 0; those after the checkpoint for a resumed one)."""

    def __init__(self, folder: str | Path, group: str, terms: Iterable[str], inputs: Iterable[str | Path | None] = ()):
        self.group = group
        self.terms = tuple(terms)
        self.folder = check_curves_dir(folder, group, self.terms, inputs)
        self.summary: dict[str, float | int | str] = {}
        self.step: int | None = None
        self._started = False

    def _start(self, first_step: int) -> None:
        """Drop earlier rows at ``first_step`` or later; the summary restarts from the rows kept."""
        kept: dict[str, tuple[int, float | int | str]] = {}
        for term in self.terms:
            tsv = _group_dir(self.folder, self.group) / f"{term}.tsv"
            if not tsv.is_file():
                continue
            with open(tsv, encoding="utf-8", newline="") as fh:
                rows = [r for r in csv.DictReader(fh, delimiter="\t") if int(r["step"]) < first_step]
            if not rows:
                tsv.unlink()
                continue
            with open(tsv, "w", encoding="utf-8", newline="") as fh:  # a curve of ours (checked)
                writer = csv.DictWriter(fh, ["step", term], delimiter="\t", lineterminator=os.linesep)
                writer.writeheader()
                writer.writerows(rows)
            kept[term] = (int(rows[-1]["step"]), _number(rows[-1][term]))
        order = sorted(kept, key=lambda t: (kept[t][0], self.terms.index(t)))
        self.summary = {t: kept[t][1] for t in order}
        self._summary_file().unlink(missing_ok=True)
        self._started = True

    def log(self, step: int, values: dict) -> None:
        """Append one row per term of ``values`` at ``step`` (other keys are ignored)."""
        if not self._started:
            self._start(step)
        self.step = step
        group_dir = _group_dir(self.folder, self.group)
        group_dir.mkdir(parents=True, exist_ok=True)
        for term in self.terms:
            if term not in values:
                continue
            value = values[term]
            if isinstance(value, float) and not math.isfinite(value):
                value = str(value)
            tsv = group_dir / f"{term}.tsv"
            existed = tsv.is_file()
            with open(tsv, "a", encoding="utf-8", newline="") as fh:
                writer = csv.DictWriter(fh, ["step", term], delimiter="\t", lineterminator=os.linesep)
                if not existed:
                    writer.writeheader()
                writer.writerow({"step": step, term: value})
            self.summary[term] = value

    def _summary_file(self) -> Path:
        return _summary_path(self.folder)

    def end(self) -> None:
        """Write the summary (``metrics.json``: the last value of each term, the last step);
        nothing when no row was logged."""
        if not self._started:
            return
        data: dict = {self.group: self.summary, "step": self.step}
        tmp = self._summary_file().with_name(f".{SUMMARY}.tmp")
        tmp.write_text(json.dumps(data, indent=4) + "\n", encoding="utf-8")
        os.replace(tmp, self._summary_file())


def _number(text: str) -> float | int | str:
    try:
        return int(text)
    except ValueError:
        try:
            return float(text)
        except ValueError:
            return text
