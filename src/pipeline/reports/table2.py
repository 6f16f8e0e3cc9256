"""Table II, the ablation: overall Chamfer (mm) per synthetic scene and the mean for the
classical MVS + TSDF baseline, the plain 2DGS baseline, each variant of params
``ablation.run`` and the full method, with which components each row has (dense init,
L_gcf, L_nor). Sources: ``reports/baseline/SCENE.json`` (MVS + TSDF),
``reports/variants/VARIANT/SCENE.json`` (the variants), ``reports/metrics/SCENE.json``
(the full method) and ``reports/limit/SCENE.json`` (the 3-view limit: the ground truth cut
to what the input views see, :mod:`pipeline.evaluation.limit`); every cell is a
measurement of this pipeline. Accuracy and completeness are given beside overall, so a
reader sees on which side each row loses to the limit."""
from __future__ import annotations

import csv
import io
from pathlib import Path

from pipeline.config import LossConfig, VariantConfig, merged_section
from pipeline.evaluation.record import Chamfer
from pipeline.reports.read import ReportError, read_json

MVS_TSDF = "MVS + TSDF (classical)"
FULL = "full method"
LIMIT = "3-view limit (GT seen by the input views)"
NOT_A_METHOD = (MVS_TSDF, LIMIT)  # rows without the method's components


def _cell(path: Path, chamfer: str) -> dict:
    """``overall``, ``accuracy``, ``completeness`` (Chamfer, mm) and ``covered`` (GT covered
    fraction) of the report at ``path``, whose Chamfer figures sit under the dotted key
    ``chamfer``."""
    data = read_json(path, "report", "run `dvc repro` first")
    for k in chamfer.split("."):
        if not isinstance(data, dict) or k not in data:
            raise ReportError(f"{path}: missing `{chamfer}`")
        data = data[k]
    c = Chamfer.parse(data, f"{path}: {chamfer}")
    return {**c.figures(f"{path}: {chamfer}"), "covered": c.covered_fraction(f"{path}: {chamfer}")}


def _components(params: dict, variant: VariantConfig | None) -> dict[str, bool | None]:
    loss = merged_section(LossConfig, "loss", params, variant.loss if variant else {})
    return {"dense_init": (variant.init if variant else "mvs") == "mvs", "gcf": loss.lambda_gcf > 0,
            "nor": loss.lambda_nor > 0}


def build_table2(params: dict, scenes: list[str], run: list[str], variants: dict[str, VariantConfig],
                 metrics_dir: str | Path, variants_dir: str | Path, baseline_dir: str | Path,
                 limit_dir: str | Path) -> list[dict]:
    """Rows ``{"row", "dense_init", "gcf", "nor", SCENE: overall mm ..., "mean": mm,
    "covered": {SCENE: fraction}, "accuracy": {SCENE: mm, "mean": mm}, "completeness": {...}}``
    (``covered``: :func:`~pipeline.reports.table1.covered_fraction`); the 3-view limit first."""
    sources = [(LIMIT, None, lambda s: Path(limit_dir) / f"{s}.json", "chamfer"),
               (MVS_TSDF, None, lambda s: Path(baseline_dir) / f"{s}.json", "evaluate.metrics")]
    sources += [(name, variants[name], lambda s, n=name: Path(variants_dir) / n / f"{s}.json", "chamfer")
                for name in run]
    sources.append((FULL, None, lambda s: Path(metrics_dir) / f"{s}.json", "chamfer"))
    rows = []
    for row, variant, path_of, chamfer in sources:
        cells = {s: _cell(path_of(s), chamfer) for s in scenes}
        flags = ({"dense_init": None, "gcf": None, "nor": None} if row in NOT_A_METHOD
                 else _components(params, variant))
        side = {k: {**{s: cells[s][k] for s in scenes}, "mean": sum(cells[s][k] for s in scenes) / len(scenes)}
                for k in ("accuracy", "completeness")}
        rows.append({"row": row, **flags, **{s: cells[s]["overall"] for s in scenes},
                     "mean": sum(cells[s]["overall"] for s in scenes) / len(scenes),
                     "covered": {s: cells[s]["covered"] for s in scenes}, **side})
    return rows


def read_published_ablation(path: str | Path) -> list[dict]:
    """The paper's own Table II (published figures, DTU, never measured here): rows
    ``{"dense_init", "gcf", "nor": bool, "mean_mm": float}`` from a CSV with the columns
    ``mast3r_init, l_gcf, l_nor, mean_cd_mm`` (yes/no flags; ``#`` lines are comments)."""
    path = Path(path)
    if not path.is_file():
        raise ReportError(f"{path}: published Table II file not found")
    lines = [ln for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
    rows = []
    for i, rec in enumerate(csv.DictReader(lines), start=1):
        try:
            flags = {k: {"yes": True, "no": False}[rec[col].strip()]
                     for k, col in (("dense_init", "mast3r_init"), ("gcf", "l_gcf"), ("nor", "l_nor"))}
            rows.append({**flags, "mean_mm": float(rec["mean_cd_mm"])})
        except (KeyError, ValueError, AttributeError) as exc:
            raise ReportError(f"{path}: row {i}: need mast3r_init, l_gcf, l_nor as yes/no and a number "
                              f"mean_cd_mm ({exc!r})") from exc
    return rows


def _mark(v: bool | None) -> str:
    return "—" if v is None else ("yes" if v else "no")


def markdown(rows: list[dict], scenes: list[str], commit: str, published: list[dict] | None = None) -> str:
    head = ["row", "dense init", "L_gcf", "L_nor", *scenes, "mean"]
    lines = ["# Table II: ablation on the synthetic suite (overall Chamfer, mm; lower is better)", "",
             f"Measured here by `dvc repro` (stages evaluate, variant, baseline) at commit `{commit}`, "
             "views 23/24/33 at the `data` size, the `optimize` preset of params.yaml. Rows: the 3-view "
             "limit (the ground truth cut to what the input views see, scored alike: what a method that "
             "invents nothing would score; the yardstick, not a method, so not in bold), the classical "
             "baseline, the variants of params `ablation.run` (conf/ablation), the full method.", "",
             "| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    best = min(r["mean"] for r in rows if r["row"] != LIMIT)
    for r in rows:
        cells = [r["row"], _mark(r["dense_init"]), _mark(r["gcf"]), _mark(r["nor"]),
                 *(f"{r[s]:.3f}" for s in scenes), (f"**{r['mean']:.3f}**" if r["mean"] == best else f"{r['mean']:.3f}")]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "**Accuracy / completeness** (mm): the two halves of each overall figure. The 3-view "
              "limit's accuracy is near zero by construction, and its completeness is what the surface "
              "no input view sees costs; a row's distance to it on each side says where it loses.", "",
              "| row | " + " | ".join(scenes) + " | mean |", "|" + " --- |" * (len(scenes) + 2)]
    for r in rows:
        lines.append(f"| {r['row']} | " + " | ".join(f"{r['accuracy'][s]:.3f} / {r['completeness'][s]:.3f}"
                                                     for s in (*scenes, "mean")) + " |")
    lines += ["", "**How much of each object those figures cover**: the fraction of ground-truth points "
              "within `evaluate.max_dist_mm` of the mesh. The DTU protocol leaves the others out of "
              "completeness, so a mesh that omits a region it cannot reconstruct (the classical "
              "baseline on the textureless dome) is not charged for it; the ground truth also holds "
              "sides that no input view sees, so no row reaches 1.", "",
              "| row | " + " | ".join(scenes) + " |", "|" + " --- |" * (len(scenes) + 1)]
    for r in rows:
        lines.append(f"| {r['row']} | " + " | ".join(f"{r['covered'][s]:.2f}" for s in scenes) + " |")
    if published:
        lines += ["", "## The paper's Table II (published, not measured here)", "",
                  "GCGS paper, Table II: the same components switched off, on real DTU scans (3 views, mean "
                  "Chamfer over its test scans, mm), with MASt3R as the dense init and learned priors "
                  "(DSINE, Vis-MVSNet). Figures transcribed from the paper (`data/published/"
                  "gcgs_table2_ablation.csv`); they are on other scenes and another init than the rows above, "
                  "so compare each table's pattern, not cells across tables.", "",
                  "| dense init (MASt3R) | L_gcf | L_nor | mean (DTU, published) |", "| --- | --- | --- | --- |"]
        lines += [f"| {_mark(p['dense_init'])} | {_mark(p['gcf'])} | {_mark(p['nor'])} | {p['mean_mm']:.2f} |"
                  for p in published]
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict], scenes: list[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    sides = [(k, s) for k in ("accuracy", "completeness") for s in (*scenes, "mean")]
    w.writerow(["row", "dense_init", "gcf", "nor", *scenes, "mean", *(f"{s}_covered" for s in scenes),
                *(f"{s}_{k}" for k, s in sides)])
    for r in rows:
        w.writerow([r["row"], *("" if r[k] is None else int(r[k]) for k in ("dense_init", "gcf", "nor")),
                    *(f"{r[s]:.4f}" for s in scenes), f"{r['mean']:.4f}", *(f"{r['covered'][s]:.4f}" for s in scenes),
                    *(f"{r[k][s]:.4f}" for k, s in sides)])
    return buf.getvalue()
