"""Table II, the ablation: overall Chamfer (mm) per synthetic scene and the mean for the
classical MVS + TSDF baseline, the plain 2DGS baseline, each variant of params
``ablation.run`` and the full method, with which components each row has (dense init,
L_gcf, L_nor). Sources: ``reports/baseline/SCENE.json`` (MVS + TSDF),
``reports/variants/VARIANT/SCENE.json`` (the variants) and ``reports/metrics/SCENE.json``
(the full method); every cell is a measurement of this pipeline."""
from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from pipeline.config import LossConfig, VariantConfig, merged_section
from pipeline.errors import InputError

MVS_TSDF = "MVS + TSDF (classical)"
FULL = "full method"


def _overall(path: Path, keys: tuple[str, ...]) -> float:
    if not path.is_file():
        raise InputError(f"{path}: missing report (run `dvc repro` first)")
    try:
        node = json.loads(path.read_text())
        for k in keys:
            node = node[k]
        value = float(node)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{path}: no {'.'.join(keys)} ({exc})") from exc
    if not math.isfinite(value):
        raise InputError(f"{path}: {'.'.join(keys)} is not finite ({value})")
    return value


def _components(params: dict, variant: VariantConfig | None) -> dict[str, bool | None]:
    loss = merged_section(LossConfig, "loss", params, variant.loss if variant else {})
    return {"dense_init": (variant.init if variant else "mvs") == "mvs", "gcf": loss.lambda_gcf > 0,
            "nor": loss.lambda_nor > 0}


def build_table2(params: dict, scenes: list[str], run: list[str], variants: dict[str, VariantConfig],
                 metrics_dir: str | Path, variants_dir: str | Path, baseline_dir: str | Path) -> list[dict]:
    """Rows ``{"row", "dense_init", "gcf", "nor", SCENE: mm ..., "mean": mm}``."""
    rows = [{"row": MVS_TSDF, "dense_init": None, "gcf": None, "nor": None,
             **{s: _overall(Path(baseline_dir) / f"{s}.json", ("evaluate", "metrics", "overall_mm")) for s in scenes}}]
    for name in run:
        rows.append({"row": name, **_components(params, variants[name]),
                     **{s: _overall(Path(variants_dir) / name / f"{s}.json", ("chamfer", "overall_mm")) for s in scenes}})
    rows.append({"row": FULL, **_components(params, None),
                 **{s: _overall(Path(metrics_dir) / f"{s}.json", ("chamfer", "overall_mm")) for s in scenes}})
    for r in rows:
        r["mean"] = sum(r[s] for s in scenes) / len(scenes)
    return rows


def _mark(v: bool | None) -> str:
    return "—" if v is None else ("yes" if v else "no")


def markdown(rows: list[dict], scenes: list[str], commit: str) -> str:
    head = ["row", "dense init", "L_gcf", "L_nor", *scenes, "mean"]
    lines = ["# Table II: ablation on the synthetic suite (overall Chamfer, mm; lower is better)", "",
             f"Measured here by `dvc repro` (stages evaluate, variant, baseline) at commit `{commit}`, "
             "views 23/24/33 at the `data` size, the `optimize` preset of params.yaml. Rows: the "
             "classical baseline, the variants of params `ablation.run` (conf/ablation), the full method.", "",
             "| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    best = min(r["mean"] for r in rows)
    for r in rows:
        cells = [r["row"], _mark(r["dense_init"]), _mark(r["gcf"]), _mark(r["nor"]),
                 *(f"{r[s]:.3f}" for s in scenes), (f"**{r['mean']:.3f}**" if r["mean"] == best else f"{r['mean']:.3f}")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict], scenes: list[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["row", "dense_init", "gcf", "nor", *scenes, "mean"])
    for r in rows:
        w.writerow([r["row"], *("" if r[k] is None else int(r[k]) for k in ("dense_init", "gcf", "nor")),
                    *(f"{r[s]:.4f}" for s in scenes), f"{r['mean']:.4f}"])
    return buf.getvalue()
