"""Table I: overall Chamfer distance (mm) per scene, measured here next to published figures,
and the held-out-view scores of the scenes without ground truth.

Measured rows come from the per-scene reports of this pipeline: the method from
``reports/metrics/SCENE.json`` (``gcgs score``: ``chamfer.overall_mm``) and the classical
MVS + TSDF baseline from ``reports/baseline/SCENE.json`` (``gcgs baseline``:
``evaluate.metrics.overall_mm``). Published rows come from a CSV kept in the repository
(``data/published/dtu_3view_table1.csv``: method, mean_mm, source, note, and optionally one
column per DTU scan, ``scanNN``); they are only ever shown in rows of kind ``published``.

Columns: every configured scene with ground truth. Scenes named ``scanNN`` (the DTU naming,
as in :func:`pipeline.data.dtu.load_scene`) form the DTU group, the others (the synthetic
suite) the synthetic group; each group has its mean column. The DTU mean column is always
shown because the published means are DTU means (over the papers' own test scans, not
necessarily the scans measured here).
"""
from __future__ import annotations

import csv
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.errors import MissingInputError
from pipeline.evaluation.record import Chamfer, SceneMetrics
from pipeline.jsonfile import ReportError, read_json

MEASURED = "measured here"
PUBLISHED = "published"
DTU_SCENE = re.compile(r"scan\d+")
MEAN_SYNTH = "mean_synthetic"
MEAN_DTU = "mean_dtu"
PUBLISHED_COLUMNS = ("method", "mean_mm", "source", "note")


@dataclass
class Row:
    """One row of the Chamfer table: cells map a column key (scene or mean) to mm or None."""

    method: str
    kind: str  # MEASURED or PUBLISHED
    cells: dict[str, float | None]
    commit: str = ""
    source: str = ""
    note: str = ""


@dataclass
class HeldoutRow:
    """Held-out-view scores of one scene without ground truth (``gcgs score``)."""

    scene: str
    views: int
    size: tuple[int, int]
    iou: float
    hull_iou: float
    psnr_masked_db: float | None
    mesh_iou: float | None = None  # the mesh's silhouette (absent from records written before it)


@dataclass
class Table1:
    scenes_synthetic: list[str]
    scenes_dtu: list[str]
    rows: list[Row]
    heldout: list[HeldoutRow]
    settings: dict[str, dict]  # scene -> the metrics' ``train`` section (preset, iterations ...)
    notes: list[str] = field(default_factory=list)

    @property
    def columns(self) -> list[str]:
        synth = self.scenes_synthetic + ([MEAN_SYNTH] if self.scenes_synthetic else [])
        return synth + self.scenes_dtu + [MEAN_DTU]


# --- reading ------------------------------------------------------------------------------


def read_published(path: str | Path) -> list[Row]:
    """Published rows of a CSV (columns :data:`PUBLISHED_COLUMNS`, optional ``scanNN``
    columns); an empty cell is a figure not available."""
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"{path}: published figures file not found")
    reader = csv.DictReader(io.StringIO(path.read_text()))
    header = reader.fieldnames or []
    missing = [c for c in PUBLISHED_COLUMNS if c not in header]
    if missing:
        raise ReportError(f"{path}: missing column(s) {missing}")
    extra = [c for c in header if c not in PUBLISHED_COLUMNS and not DTU_SCENE.fullmatch(c)]
    if extra:
        raise ReportError(f"{path}: unknown column(s) {extra} (allowed: {list(PUBLISHED_COLUMNS)} and scanNN)")
    rows = []
    for line, rec in enumerate(reader, start=2):
        if not rec["method"]:
            raise ReportError(f"{path}: line {line}: empty method")
        cells = {}
        for col in header:
            if col == "mean_mm" or DTU_SCENE.fullmatch(col):
                text = (rec[col] or "").strip()
                try:
                    value = float(text) if text else None
                except ValueError:
                    raise ReportError(f"{path}: line {line}: {col} must be a number or empty, got {text!r}") from None
                if value is not None and not (math.isfinite(value) and value > 0):
                    raise ReportError(f"{path}: line {line}: {col} must be a positive number of mm, got {text!r}")
                cells[MEAN_DTU if col == "mean_mm" else col] = value
        rows.append(Row(rec["method"], PUBLISHED, cells, source=rec["source"] or "", note=rec["note"] or ""))
    return rows


# --- building ----------------------------------------------------------------------------


def _mean(values: list[float | None]) -> float | None:
    return sum(values) / len(values) if values and all(v is not None for v in values) else None


def _group_means(cells: dict[str, float | None], synth: list[str], dtu: list[str]) -> dict[str, float | None]:
    out = {}
    if synth:
        out[MEAN_SYNTH] = _mean([cells.get(s) for s in synth])
    out[MEAN_DTU] = _mean([cells.get(s) for s in dtu])
    return out


def _settings_label(settings: dict[str, dict]) -> str:
    kinds = sorted({f"preset {s.get('preset', '?')}, {s.get('iterations', '?')} iterations, {s.get('backend', '?')}"
                    for s in settings.values()})
    return "; ".join(kinds)


def build_table1(scenes: dict[str, dict], metrics_dir: str | Path, baseline_dir: str | Path,
                 published_csv: str | Path, commit: str) -> Table1:
    """Table I for the configured ``scenes`` (params ``scenes``: name -> {src, gt}).

    Every configured scene needs ``metrics_dir/NAME.json``; scenes with ``gt`` also need
    ``baseline_dir/NAME.json``. ``commit`` is the commit the table is generated at, shown
    for the method's rows since the metrics files do not record one."""
    if not scenes:
        raise ReportError("params `scenes` is empty: nothing to tabulate")
    metrics_dir, baseline_dir = Path(metrics_dir), Path(baseline_dir)
    with_gt = [n for n, e in scenes.items() if (e or {}).get("gt")]
    synth = [n for n in with_gt if not DTU_SCENE.fullmatch(n)]
    dtu_measured = [n for n in with_gt if DTU_SCENE.fullmatch(n)]
    published = read_published(published_csv)
    # Published per-scan figures get their scan's column even where nothing is measured.
    dtu = dtu_measured + sorted({c for r in published for c, v in r.cells.items() if v is not None and DTU_SCENE.fullmatch(c)}
                  - set(dtu_measured), key=lambda s: int(s[4:]))
    notes: list[str] = []
    method, baseline, settings, heldout = {}, {}, {}, []
    for name in scenes:
        path = metrics_dir / f"{name}.json"
        m = SceneMetrics.read(path, "run the score stage")
        settings[name] = m.train
        if name in with_gt:
            if m.chamfer is None:
                raise ReportError(f"{path}: scene {name} has ground truth, so `chamfer` figures are expected")
            method[name] = m.chamfer.figures(str(path))["overall"]
            if not m.chamfer.valid:
                notes.append(f"{name}: the method's evaluation was flagged invalid ({path}: "
                             f"{'; '.join(m.chamfer.problems or ['no reason given'])})")
            bpath = baseline_dir / f"{name}.json"
            b = read_json(bpath, f"baseline report of scene {name}", "run the baseline stage")
            if b.get("evaluate", {}).get("metrics"):
                bc = Chamfer.parse(b["evaluate"]["metrics"], f"{bpath}: evaluate.metrics")
                baseline[name] = (bc.figures(f"{bpath}: evaluate.metrics")["overall"], b.get("commit", "unknown"))
            else:
                baseline[name] = (None, b.get("commit", "unknown"))
                notes.append(f"{name}: no MVS + TSDF Chamfer in {bpath} (evaluate status "
                             f"{b.get('evaluate', {}).get('status', 'absent')!r})")
        else:
            h = m.heldout
            if h is None:
                raise ReportError(f"{path}: scene {name} has no ground truth, so `heldout` scores are expected")
            heldout.append(HeldoutRow(name, h.views, h.size, h.iou_mean, h.hull_iou_mean, h.psnr_masked_db_mean,
                                          h.mesh_iou_mean))
    rows = []
    if with_gt:
        cells = {n: method[n] for n in with_gt}
        rows.append(Row("GCGS (this pipeline)", MEASURED, cells | _group_means(cells, synth, dtu_measured), commit=commit,
                        source="reports/metrics/SCENE.json (gcgs score)",
                        note=_settings_label({n: settings[n] for n in with_gt})))
        cells = {n: baseline[n][0] for n in with_gt}
        commits = sorted({baseline[n][1] for n in with_gt})
        rows.append(Row("MVS + TSDF (classical baseline)", MEASURED, cells | _group_means(cells, synth, dtu_measured),
                        commit=", ".join(commits), source="reports/baseline/SCENE.json (gcgs baseline)",
                        note="plane-sweep MVS depth maps of the input views fused by TSDF"))
    rows += published
    return Table1(synth, dtu, rows, heldout, settings, notes)


# --- writing ------------------------------------------------------------------------------


def _header(key: str) -> str:
    return {MEAN_SYNTH: "mean (synthetic)", MEAN_DTU: "mean (DTU)"}.get(key, key)


def _cell(value: float | None, kind: str) -> str:
    if value is None:
        return ""
    return f"{value:.3f}" if kind == MEASURED else f"{value:g}"


def markdown(table: Table1, commit: str) -> str:
    cols = table.columns
    lines = [
        "# Table I: overall Chamfer distance (mm, lower is better)", "",
        f"Generated by `gcgs table1` (DVC stage `table1`) at commit `{commit}`. Overall Chamfer = (accuracy + "
        "completeness) / 2 of the reconstructed mesh against the scene's ground truth, DTU protocol "
        "(`src/pipeline/evaluation/dtu_eval.py`), world mm, 3 input views (params `data.views`).", "",
        f"- Rows **{MEASURED}**: computed by this repository on this machine. The method's cells are "
        "`chamfer.overall_mm` of `reports/metrics/SCENE.json`, whose settings are listed below; those files record "
        "no commit, so the commit shown is the table's (its dvc.lock pins their hashes). The baseline's cells are "
        "`evaluate.metrics.overall_mm` of `reports/baseline/SCENE.json`, at the commit those reports record.",
        f"- Rows **{PUBLISHED}**: figures from papers, kept in `data/published/dtu_3view_table1.csv` with their "
        "source; never computed here, and on the papers' DTU test scans, not on the scenes measured here. An empty "
        "published cell is a figure not available.",
        "- Columns: `synth_*` are the synthetic suite (exact ground truth, rendered by `gcgs synth`); `scanNN` "
        "are DTU scans with official evaluation files. A mean is over the scenes of its group shown here (empty "
        "when one is missing).", "",
        "| method | kind | " + " | ".join(_header(c) for c in cols) + " | commit | source | note |",
        "| --- | --- | " + " | ".join("---:" for _ in cols) + " | --- | --- | --- |",
    ]
    for r in table.rows:
        lines.append(f"| {r.method} | {r.kind} | " + " | ".join(_cell(r.cells.get(c), r.kind) for c in cols)
                     + f" | {f'`{r.commit}`' if r.commit else ''} | {r.source} | {r.note} |")
    if table.heldout:
        lines += ["", "## Real scans without ground truth: held-out views", "",
                  "Every view of the scan not used for training, at the stored held-out size: mask IoU of the "
                  "mesh's silhouette against the view's object mask, the same IoU of the trained surfels' alpha > 0.5 "
                  "and of the visual hull of the input masks (the trivial reference), and PSNR of the surfels' "
                  "colour over the mask's pixels "
                  "(`src/pipeline/evaluation/heldout.py`; `heldout` of `reports/metrics/SCENE.json`). "
                  f"Measured here at commit `{commit}`.", "",
                  "| scene | held-out views | size (px) | mesh IoU | surfels IoU | visual hull IoU | masked PSNR (dB) |",
                  "| --- | ---: | --- | ---: | ---: | ---: | ---: |"]
        for h in table.heldout:
            psnr = "" if h.psnr_masked_db is None else f"{h.psnr_masked_db:.2f}"
            mesh = "" if h.mesh_iou is None else f"{h.mesh_iou:.3f}"
            lines.append(f"| {h.scene} | {h.views} | {'x'.join(map(str, h.size))} | {mesh} | {h.iou:.3f} | "
                         f"{h.hull_iou:.3f} | {psnr} |")
    lines += ["", "## Settings of the measured runs", "",
              "From the `train` section of `reports/metrics/SCENE.json` (the optimize stage's record).", "",
              "| scene | preset | iterations | backend | masks | surfels (init -> final) |",
              "| --- | --- | ---: | --- | --- | --- |"]
    for name, s in table.settings.items():
        lines.append(f"| {name} | {s.get('preset', '')} | {s.get('iterations', '')} | {s.get('backend', '')} | "
                     f"{s.get('masks', '')} | {s.get('surfels_init', '')} -> {s.get('surfels_final', '')} |")
    if table.notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in table.notes]
    return "\n".join(lines) + "\n"


def csv_text(table: Table1) -> str:
    """The Chamfer table as CSV: method, kind, one column per scene and mean (mm, empty when
    not available), commit, source, note."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["method", "kind", *table.columns, "commit", "source", "note"])
    for r in table.rows:
        w.writerow([r.method, r.kind, *(_csv_value(r.cells.get(c), r.kind) for c in table.columns),
                    r.commit, r.source, r.note])
    return buf.getvalue()


def _csv_value(value: float | None, kind: str) -> str:
    if value is None:
        return ""
    return f"{value:.4f}" if kind == MEASURED else f"{value:g}"


def read_table_csv(text: str, where: str = "table CSV") -> list[dict]:
    """Parse a table written by :func:`csv_text`: rows with their cells as floats or None.
    Raises naming ``where`` when the header is not Table I's or a cell is not a number."""
    reader = csv.DictReader(io.StringIO(text))
    header = reader.fieldnames or []
    if header[:2] != ["method", "kind"] or header[-3:] != ["commit", "source", "note"] or MEAN_DTU not in header:
        raise ReportError(f"{where}: not a Table I CSV (header {header})")
    rows = []
    for line, rec in enumerate(reader, start=2):
        if rec["kind"] not in (MEASURED, PUBLISHED):
            raise ReportError(f"{where}: line {line}: kind must be {MEASURED!r} or {PUBLISHED!r}, got {rec['kind']!r}")
        cells = {}
        for col in header[2:-3]:
            text = rec[col]
            try:
                cells[col] = float(text) if text else None
            except ValueError:
                raise ReportError(f"{where}: line {line}: {col} must be a number or empty, got {text!r}") from None
        rows.append({"method": rec["method"], "kind": rec["kind"], "cells": cells, "commit": rec["commit"],
                     "source": rec["source"], "note": rec["note"]})
    return rows
