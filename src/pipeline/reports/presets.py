"""The preset ladder (docs/presets.md): one row per (preset, scene, seed) training, the
per-preset summary, the check that more time never buys a worse surface, and the plot.

``reports/presets.csv`` holds the rows; ``reports/presets.md`` the summary table that the
README's presets table is taken from; ``reports/presets.png`` mean Chamfer against training
CPU time with the seeds' spread. ``scripts/presets.py`` runs the trainings.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline import atomic
from pipeline.errors import InputError

COLUMNS = ("preset", "scene", "seed", "overall_mm", "accuracy_mm", "completeness_mm", "train_wall_s", "train_cpu_s",
           "peak_rss_mb", "commit")
LADDER = ("quick", "fast", "balanced", "long", "paper")
# A step of the ladder "rises" when its mean overall Chamfer exceeds the previous step's by
# more than this (mm): differences under it are within the seeds' spread (docs/presets.md).
RISE_TOLERANCE_MM = 0.01


@dataclass(frozen=True)
class PresetSummary:
    """One preset over its runs: per-scene means and half-ranges over the seeds, and the mean
    over the scenes of the per-scene means (mm; seconds; MB)."""

    preset: str
    scenes: tuple[str, ...]
    seeds: int                        # seeds per scene (the fewest any scene has)
    overall_by_scene: dict[str, tuple[float, float]]   # scene -> (mean, half-range)
    overall_mm: float
    accuracy_mm: float
    completeness_mm: float
    train_cpu_s: float
    train_wall_s: float
    peak_rss_mb: float                # the largest of the runs


def read_rows(path: str | Path) -> list[dict]:
    """The rows of ``reports/presets.csv``, numbers as floats (seed as int)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: not found (run scripts/presets.py)")
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != COLUMNS:
            raise InputError(f"{path}: columns {reader.fieldnames} are not {list(COLUMNS)}")
        rows = []
        for n, r in enumerate(reader, start=2):
            try:
                rows.append({**r, "seed": int(r["seed"]),
                             **{k: float(r[k]) for k in COLUMNS[3:-1]}})
            except ValueError as exc:
                raise InputError(f"{path}: line {n}: {exc}") from exc
    return rows


def write_rows(rows: list[dict], path: str | Path) -> None:
    """``rows`` as CSV in ladder order, then scene, then seed."""
    order = {p: i for i, p in enumerate(LADDER)}
    rows = sorted(rows, key=lambda r: (order.get(r["preset"], len(order)), r["preset"], r["scene"], r["seed"]))
    with atomic.atomic_file(path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r[k] for k in COLUMNS})


def summarize(rows: list[dict]) -> list[PresetSummary]:
    """Per preset present, in ladder order. Scene means first, then their mean: a scene with
    more seeds does not weigh more."""
    out = []
    presets = [p for p in LADDER if any(r["preset"] == p for r in rows)]
    presets += sorted({r["preset"] for r in rows} - set(presets))
    for preset in presets:
        rs = [r for r in rows if r["preset"] == preset]
        scenes = tuple(sorted({r["scene"] for r in rs}))
        by_scene = {s: [r for r in rs if r["scene"] == s] for s in scenes}

        def scene_mean(key: str) -> float:
            return float(np.mean([np.mean([r[key] for r in by_scene[s]]) for s in scenes]))

        overall = {}
        for s in scenes:
            v = np.array([r["overall_mm"] for r in by_scene[s]])
            overall[s] = (float(v.mean()), float((v.max() - v.min()) / 2))
        out.append(PresetSummary(
            preset=preset, scenes=scenes, seeds=min(len(v) for v in by_scene.values()), overall_by_scene=overall,
            overall_mm=scene_mean("overall_mm"), accuracy_mm=scene_mean("accuracy_mm"),
            completeness_mm=scene_mean("completeness_mm"), train_cpu_s=scene_mean("train_cpu_s"),
            train_wall_s=scene_mean("train_wall_s"), peak_rss_mb=float(max(r["peak_rss_mb"] for r in rs))))
    return out


def rises(summaries: list[PresetSummary], tolerance_mm: float = RISE_TOLERANCE_MM) -> list[tuple[str, str, float]]:
    """The steps of the ladder (consecutive presets present, in ladder order, on the same
    scenes) where more time bought a worse mean surface: ``(previous, preset, rise in mm)``."""
    found = []
    for prev, cur in zip(summaries, summaries[1:]):
        if prev.scenes != cur.scenes:
            raise InputError(f"presets {prev.preset} and {cur.preset} were run on different scenes "
                             f"({', '.join(prev.scenes)} / {', '.join(cur.scenes)}): their means do not compare")
        if cur.overall_mm > prev.overall_mm + tolerance_mm:
            found.append((prev.preset, cur.preset, cur.overall_mm - prev.overall_mm))
    return found


def markdown(summaries: list[PresetSummary], commits: list[str]) -> str:
    """The summary table (overall per scene with the seeds' half-range, their mean, accuracy,
    completeness, time, peak RSS) and the ladder check."""
    scenes = summaries[0].scenes if summaries else ()
    head = ["preset", *scenes, "mean", "accuracy", "completeness", "train CPU s", "train wall s", "peak RSS MB"]
    lines = [
        "# The preset ladder",
        "",
        f"Written by `scripts/presets.py` from `reports/presets.csv` (commit {', '.join(sorted(set(commits)))}). "
        "Overall Chamfer in mm per scene, mean ± half the range over the seeds; the other columns are the "
        "mean over scenes of the per-scene means (peak RSS: the largest run).",
        "",
        "| " + " | ".join(head) + " |",
        "| " + " | ".join("---" for _ in head) + " |",
    ]
    for s in summaries:
        cells = [f"`{s.preset}` ({s.seeds} seeds)"]
        cells += [f"{s.overall_by_scene[sc][0]:.3f} ± {s.overall_by_scene[sc][1]:.3f}" if sc in s.overall_by_scene
                  else "-" for sc in scenes]
        cells += [f"{s.overall_mm:.3f}", f"{s.accuracy_mm:.3f}", f"{s.completeness_mm:.3f}", f"{s.train_cpu_s:.0f}",
                  f"{s.train_wall_s:.0f}", f"{s.peak_rss_mb:.0f}"]
        lines.append("| " + " | ".join(cells) + " |")
    # A preset run on fewer scenes (or seeds) than the others is not yet a step of the ladder.
    full = [x for x in summaries if x.scenes == scenes and x.seeds == summaries[0].seeds]
    partial = [x.preset for x in summaries if x not in full]
    found = rises(full)
    lines += ["", "More time never bought a worse mean surface (beyond "
              f"{RISE_TOLERANCE_MM} mm)." if not found else
              "More time bought a worse mean surface: " + "; ".join(
                  f"`{b}` is {d:.3f} mm above `{a}`" for a, b, d in found) + "."]
    if partial:
        lines.append(f"Not compared (fewer scenes or seeds than `{summaries[0].preset}`): "
                     + ", ".join(f"`{p}`" for p in partial) + ".")
    return "\n".join(lines) + "\n"


def write_plot(rows: list[dict], summaries: list[PresetSummary], path: str | Path) -> None:
    """Mean overall Chamfer against mean training CPU per preset, each seed's scene-mean as a
    dot (where every scene has that seed), the ladder joined."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    t = [s.train_cpu_s for s in summaries]
    e = [s.overall_mm for s in summaries]
    ax.plot(t, e, "-o", c="tab:red", zorder=3)
    for s in summaries:
        rs = [r for r in rows if r["preset"] == s.preset]
        for seed in sorted({r["seed"] for r in rs}):
            per = [r for r in rs if r["seed"] == seed]
            if {r["scene"] for r in per} == set(s.scenes):
                ax.scatter(np.mean([r["train_cpu_s"] for r in per]), np.mean([r["overall_mm"] for r in per]),
                           c="tab:gray", s=12, zorder=2)
        ax.annotate(s.preset, (s.train_cpu_s, s.overall_mm), xytext=(5, 5), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("training CPU time, s (mean over scenes; one thread)")
    ax.set_ylabel("overall Chamfer, mm (mean over scenes)")
    ax.set_title("presets: red = mean over seeds, gray = one seed")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic.atomic_file(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def write_report(rows: list[dict], csv_path: str | Path, md_path: str | Path, png_path: str | Path) -> list[PresetSummary]:
    """CSV, Markdown summary and plot of ``rows``."""
    if not rows:
        raise InputError(f"{csv_path}: no measured run to write")
    write_rows(rows, csv_path)
    summaries = summarize(rows)
    atomic.write_text(md_path, markdown(summaries, [r["commit"] for r in rows]))
    write_plot(rows, summaries, png_path)
    return summaries
