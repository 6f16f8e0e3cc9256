"""The speed-accuracy trade: per-cell reports (``gcgs variant`` metrics) gathered into one
table, the Pareto front of (time, Chamfer), and the plot (docs/speed_accuracy.md)."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from pipeline import atomic
from pipeline.errors import InputError
from pipeline.evaluation.record import SceneMetrics

COLUMNS = ("scene", "cell", "overall_mm", "accuracy_mm", "completeness_mm", "train_wall_s", "train_cpu_s",
           "peak_rss_mb", "iterations", "surfels_final", "init", "changes", "load_average_1min", "commit", "pareto")


def pareto_front(time_s: np.ndarray, error: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the cells no other cell beats on both time and error (lower is
    better on both; a tie on one and a win on the other dominates)."""
    t, e = np.asarray(time_s, float), np.asarray(error, float)
    better_or_equal = (t[None, :] <= t[:, None]) & (e[None, :] <= e[:, None])
    strictly = (t[None, :] < t[:, None]) | (e[None, :] < e[:, None])
    return ~np.any(better_or_equal & strictly, axis=1)


def collect_cells(folder: str | Path, scenes: list[str], cells: list[str]) -> list[dict]:
    """One row per existing ``folder/SCENE/CELL.json``; the Pareto flag is per scene."""
    rows = []
    for scene in scenes:
        scene_rows = []
        for cell in cells:
            path = Path(folder) / scene / f"{cell}.json"
            if not path.is_file():
                continue
            m = SceneMetrics.read(path, "run the speed-accuracy cells")
            if m.chamfer is None or m.variant is None:
                raise InputError(f"{path}: not a variant report with Chamfer figures")
            ch, tm, tr, var = m.chamfer.to_json(), m.timing, m.train, m.variant
            changes = {k: var[k] for k in ("optimize", "loss", "mesh") if var.get(k)}
            scene_rows.append({
                "scene": scene, "cell": cell, "overall_mm": ch["overall_mm"], "accuracy_mm": ch["accuracy_mm"],
                "completeness_mm": ch["completeness_mm"], "train_wall_s": tm["wall_s"], "train_cpu_s": tm["cpu_s"],
                "peak_rss_mb": tm["peak_rss_mb"], "iterations": tr["iterations"], "surfels_final": tr["surfels_final"],
                "init": var["init"], "changes": json.dumps(changes, sort_keys=True),
                "load_average_1min": (m.provenance or {}).get("load_average_1min"),
                "commit": (m.provenance or {}).get("commit"),
            })
        if scene_rows:
            front = pareto_front([r["train_cpu_s"] for r in scene_rows], [r["overall_mm"] for r in scene_rows])
            for r, f in zip(scene_rows, front):
                r["pareto"] = bool(f)
        rows += scene_rows
    return rows


def write_report(rows: list[dict], csv_path: Path, png_path: Path, labels: dict[str, str] | None = None) -> None:
    """The table as CSV and the plot (training wall time on x, overall Chamfer on y, the
    Pareto front joined, cells named; ``labels`` maps a cell to a preset name shown bold)."""
    if not rows:
        raise InputError(f"{csv_path}: no measured cell to write")
    with atomic.atomic_file(csv_path) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k) for k in COLUMNS})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = labels or {}
    scenes = sorted({r["scene"] for r in rows})
    # Per scene: every cell, then a zoom on the cells within 10% of the best Chamfer (a bad
    # init squashes the others into one line otherwise).
    fig, axes = plt.subplots(len(scenes), 2, figsize=(13, 4.8 * len(scenes)), squeeze=False)
    for (ax_all, ax_zoom), scene in zip(axes, scenes):
        rs = [r for r in rows if r["scene"] == scene]
        best = min(r["overall_mm"] for r in rs)
        for ax, cells, title in ((ax_all, rs, "all cells"),
                                 (ax_zoom, [r for r in rs if r["overall_mm"] <= 1.1 * best], "within 10% of the best")):
            t = np.array([r["train_cpu_s"] for r in cells])
            e = np.array([r["overall_mm"] for r in cells])
            on = np.array([r["pareto"] for r in cells])
            ax.scatter(t[~on], e[~on], c="tab:gray", label="measured cell")
            ax.scatter(t[on], e[on], c="tab:red", label="Pareto front")
            order = np.argsort(t[on])
            ax.plot(t[on][order], e[on][order], c="tab:red", lw=1)
            for k, (r, x, y) in enumerate(zip(cells, t, e)):
                name = labels.get(r["cell"])
                ax.annotate(r["cell"] + (f" = preset {name}" if name else ""), (x, y), fontsize=7,
                            fontweight="bold" if name else "normal", xytext=(4, 4 + 7 * (k % 3)),
                            textcoords="offset points")
            ax.set_xscale("log")
            ax.set_xlabel("optimize CPU time, s (2-core machine; robust to other load)")
            ax.set_ylabel("overall Chamfer, mm")
            ax.set_title(f"{scene}: {title}")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic.atomic_file(png_path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)
