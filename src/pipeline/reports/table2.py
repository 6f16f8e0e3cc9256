"""Table II, the ablation: overall Chamfer (mm) per synthetic scene and the mean for the
classical MVS + TSDF baseline, the plain 2DGS baseline, each variant of params
``ablation.run`` and the full method, with which components each row has (dense init,
L_gcf, L_nor). Sources: ``reports/baseline/SCENE.json`` (MVS + TSDF),
``reports/variants/VARIANT/SCENE.json`` (the variants), ``reports/metrics/SCENE.json``
(the full method) and ``reports/limit/SCENE.json`` (the 3-view limit: the ground truth cut
to what the input views see, :mod:`pipeline.synth.limit`); every cell is a
measurement of this pipeline. Accuracy and completeness are given beside overall, so a
reader sees on which side each row loses to the limit.

Seeds: a variant named ``ROW_seedK`` is row ``ROW`` trained with another seed (``full_seedK``:
the full method, whose seed-0 run is the main pipeline). A row with seed replicates shows the
mean over its seeds and, beside it, the spread: half the range (max - min) of the overall
figure over the seeds, so a difference between rows smaller than their spreads is none."""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from pipeline.config.ablation import SEED_REPLICATE, VariantConfig
from pipeline.config.loss import LossConfig
from pipeline.config.mesh import MeshConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.config.params import merged_section
from pipeline.evaluation.record import Chamfer
from pipeline.jsonfile import ReportError, read_json

MVS_TSDF = "MVS + TSDF (classical)"
FULL = "full method"
LIMIT = "3-view limit (GT seen by the input views)"
EXACT_DEPTH = "exact depth through the same meshing"
NOT_A_METHOD = (MVS_TSDF, LIMIT, EXACT_DEPTH)  # rows without the method's components
YARDSTICKS = (LIMIT, EXACT_DEPTH)  # not methods: never the best row
# The method's components (CSV column: Markdown header), in the table's column order.
COMPONENTS = {"dense_init": "dense init", "gcf": "L_gcf", "nor": "L_nor", "mv": "L_mv", "photo_reset": "photo reset",
              "ncc_support": "NCC support weights", "mv_textured": "L_mv points on texture",
              "mv_ceiling": "L_mv cost ceiling",
              "means_lr_held": "means lr held", "smooth": "L_smooth (flat patches)",
              "init_depth_mesh": "init depth in the mesh"}


# Accuracy beyond this distance (mm) is Table II's tail: the bands of dtu_eval.by_distance from here up.
FAR_MM = 1.0


def seed_groups(run: list[str]) -> dict[str, list[str]]:
    """Rows of ``run`` in order, each with its variants: ``{"no_gcf": ["no_gcf", "no_gcf_seed1"],
    "full": ["full_seed1", ...]}``; a replicate whose row is not in ``run`` is a row of its
    own replicates (``full`` is the main pipeline's row)."""
    groups: dict[str, list[str]] = {}
    for name in run:
        m = SEED_REPLICATE.match(name)
        groups.setdefault(m["row"] if m else name, []).append(name)
    return groups


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
    seen2 = (c.accuracy_by_views_seen or {}).get("2+") or {}
    gt_seen = c.completeness_by_views_seen or {}
    acc_far, acc_far_fraction = c.accuracy_beyond(FAR_MM)
    return {**c.figures(f"{path}: {chamfer}"), "covered": c.covered_fraction(f"{path}: {chamfer}"),
            "seen2": _finite(seen2.get("accuracy_mm")), "seen2_fraction": _finite(seen2.get("fraction")),
            "acc_far": acc_far, "acc_far_fraction": acc_far_fraction,
            **{f"comp_seen{g}": _finite((gt_seen.get(g) or {}).get("completeness_mm")) for g in ("2+", "1", "0")}}


def _finite(x) -> float:
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else math.nan


def _components(params: dict, variant: VariantConfig | None) -> dict[str, bool | None]:
    loss = merged_section(LossConfig, "loss", params, variant.loss if variant else {})
    optimize = merged_section(OptimizeConfig, "optimize", params, variant.optimize if variant else {})
    mesh = merged_section(MeshConfig, "mesh", params, variant.mesh if variant else {})
    return {"dense_init": (variant.init if variant else "mvs") == "mvs", "gcf": loss.lambda_gcf > 0,
            "nor": loss.lambda_nor > 0, "mv": loss.lambda_mv > 0 or loss.lambda_mvgeo > 0,
            "photo_reset": optimize.photo_reset.enabled, "ncc_support": loss.mv_ncc_gamma > 0,
            "mv_textured": optimize.mv_textured_points,
            "mv_ceiling": loss.mv_max_cost < 2.0,  # 1 - NCC <= 2: a ceiling of 2 drops no pair
            "means_lr_held": optimize.lr.means_final >= optimize.lr.means,
            "smooth": loss.lambda_smooth > 0,
            "init_depth_mesh": mesh.init_depth_rel_tol > 0}


def _row(row: str, flags: dict, runs: list[dict[str, dict]], scenes: list[str]) -> dict:
    """One table row from its runs (one per seed; each ``{scene: cell}``): figures are means
    over the runs, ``spread`` half the range of the overall figure per scene and of the mean."""
    def avg(xs):
        return sum(xs) / len(xs)

    scene_mean = [avg([run[s]["overall"] for s in scenes]) for run in runs]
    side = {k: {**{s: avg([run[s][k] for run in runs]) for s in scenes}}
            for k in ("accuracy", "completeness", "seen2", "seen2_fraction", "acc_far", "acc_far_fraction",
                      "comp_seen2+", "comp_seen1", "comp_seen0")}
    for k in side:
        side[k]["mean"] = avg([side[k][s] for s in scenes])
    return {"row": row, **flags, **{s: avg([run[s]["overall"] for run in runs]) for s in scenes},
            "mean": avg(scene_mean), "covered": {s: avg([run[s]["covered"] for run in runs]) for s in scenes}, **side,
            "seeds": len(runs),
            "spread": {**{s: (max(r[s]["overall"] for r in runs) - min(r[s]["overall"] for r in runs)) / 2
                          for s in scenes}, "mean": (max(scene_mean) - min(scene_mean)) / 2}}


def build_table2(params: dict, scenes: list[str], run: list[str], variants: dict[str, VariantConfig],
                 metrics_dir: str | Path, variants_dir: str | Path, baseline_dir: str | Path,
                 limit_dir: str | Path) -> list[dict]:
    """Rows ``{"row", "dense_init", "gcf", "nor", SCENE: overall mm ..., "mean": mm,
    "covered": {SCENE: fraction}, "accuracy": {SCENE: mm, "mean": mm}, "completeness": {...}}``
    (``covered``: :func:`~pipeline.reports.table1.covered_fraction`); the 3-view limit first,
    then the exact-depth yardstick (the limit report's ``exact_depth``)."""
    def variant_path(name):
        return lambda s: Path(variants_dir) / name / f"{s}.json"

    groups = seed_groups(run)
    full_runs = [lambda s: Path(metrics_dir) / f"{s}.json"] + [variant_path(n) for n in groups.pop("full", [])]
    sources = [(LIMIT, None, [lambda s: Path(limit_dir) / f"{s}.json"], "chamfer"),
               (EXACT_DEPTH, None, [lambda s: Path(limit_dir) / f"{s}.json"], "exact_depth"),
               (MVS_TSDF, None, [lambda s: Path(baseline_dir) / f"{s}.json"], "evaluate.metrics")]
    sources += [(row, variants[names[0]], [variant_path(n) for n in names], "chamfer") for row, names in groups.items()]
    sources.append((FULL, None, full_runs, "chamfer"))
    rows = []
    for row, variant, paths_of, chamfer in sources:
        runs = [{s: _cell(path_of(s), chamfer) for s in scenes} for path_of in paths_of]
        flags = dict.fromkeys(COMPONENTS) if row in NOT_A_METHOD else _components(params, variant)
        rows.append(_row(row, flags, runs, scenes))
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


def _header(columns: list[str]) -> list[str]:
    return ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]


def markdown(rows: list[dict], scenes: list[str], commit: str, published: list[dict] | None = None) -> str:
    head = ["row", *COMPONENTS.values(), *scenes, "mean", "seeds"]
    lines = ["# Table II: ablation on the synthetic suite (overall Chamfer, mm; lower is better)", "",
             f"Measured here by `dvc repro` (stages evaluate, variant, baseline) at commit `{commit}`, "
             "views 23/24/33 at the `data` size, the `optimize` preset of params.yaml. Rows: the 3-view "
             "limit (the ground truth cut to what the input views see, scored alike: what a method that "
             "invents nothing would score), exact depth through the same meshing (the mesh stage's TSDF "
             "fed the ground truth's depth at the input views: what the method would score with perfect "
             "depth, so the limit's gap to it is the meshing's cost and its gap to the method training's); "
             "both are yardsticks, not methods, so never in bold; the classical "
             "baseline, the variants of params `ablation.run` (conf/ablation), the full method. A row "
             "run with several training seeds gives the mean over them and ± half their range: a "
             "difference between two rows smaller than their spreads is none.", "", *_header(head)]
    best = min(r["mean"] for r in rows if r["row"] not in YARDSTICKS)
    for r in rows:
        def fig(key, bold=False):
            text = f"**{r[key]:.3f}**" if bold else f"{r[key]:.3f}"
            return f"{text} ± {r['spread'][key]:.3f}" if r["seeds"] > 1 else text

        cells = [r["row"], *(_mark(r[k]) for k in COMPONENTS), *(fig(s) for s in scenes),
                 fig("mean", r["mean"] == best), str(r["seeds"])]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "**Accuracy / completeness** (mm): the two halves of each overall figure. The 3-view "
              "limit's accuracy is near zero by construction, and its completeness is what the surface "
              "no input view sees costs; a row's distance to it on each side says where it loses.", "",
              *_header(["row", *scenes, "mean"])]
    for r in rows:
        lines.append(f"| {r['row']} | " + " | ".join(f"{r['accuracy'][s]:.3f} / {r['completeness'][s]:.3f}"
                                                     for s in (*scenes, "mean")) + " |")
    lines += ["", "**Accuracy on surface seen by >= 2 input views** (mm; in brackets the share of the mesh "
              "there): mesh points whose nearest GT point at least two input views see "
              "(`pipeline.evaluation.seen`), the surface the views triangulate. A row worse here than "
              "MVS+TSDF has moved well-seen surface away from where the views put it (drift), which no "
              "guess at unseen surface explains.", "", *_header(["row", *scenes, "mean"])]
    for r in rows:
        if not all(math.isfinite(r["seen2"][s]) for s in scenes):
            continue
        lines.append(f"| {r['row']} | " + " | ".join(f"{r['seen2'][s]:.3f} ({100 * r['seen2_fraction'][s]:.0f}%)"
                                                     for s in scenes) + f" | {r['seen2']['mean']:.3f} |")
    lines += ["", f"**Accuracy beyond {FAR_MM:g} mm** (mm; in brackets the share of the mesh there): the part "
              f"of the accuracy mean that mesh samples more than {FAR_MM:g} mm from the GT carry "
              "(`dtu_eval.by_distance`). A tail that a filter could remove, where the rest of the "
              "accuracy is a small offset everywhere that only better geometry fixes.", "",
              *_header(["row", *scenes, "mean"])]
    for r in rows:
        if not all(math.isfinite(r["acc_far"][s]) for s in scenes):
            continue
        lines.append(f"| {r['row']} | " + " | ".join(f"{r['acc_far'][s]:.3f} ({100 * r['acc_far_fraction'][s]:.1f}%)"
                                                     for s in scenes) + f" | {r['acc_far']['mean']:.3f} |")
    lines += ["", "**Completeness by how many input views see the GT surface** (mm; >= 2 / 1 / none): GT "
              "points far from the mesh where >= 2 views see them are holes in triangulated surface; where one "
              "view sees them, surface one view's photometric loss must place; where none does, surface only "
              "invention covers (the 3-view limit's figure there is what leaving it out costs).", "",
              *_header(["row", *scenes, "mean"])]
    for r in rows:
        groups = ("comp_seen2+", "comp_seen1", "comp_seen0")
        if not all(math.isfinite(r[g][s]) for g in groups for s in scenes):
            continue
        lines.append(f"| {r['row']} | " + " | ".join(" / ".join(f"{r[g][s]:.2f}" for g in groups)
                                                     for s in (*scenes, "mean")) + " |")
    lines += ["", "**How much of each object those figures cover**: the fraction of ground-truth points "
              "within `evaluate.max_dist_mm` of the mesh. The DTU protocol leaves the others out of "
              "completeness, so a mesh that omits a region it cannot reconstruct (the classical "
              "baseline on the textureless dome) is not charged for it; the ground truth also holds "
              "sides that no input view sees, so no row reaches 1.", "", *_header(["row", *scenes])]
    for r in rows:
        lines.append(f"| {r['row']} | " + " | ".join(f"{r['covered'][s]:.2f}" for s in scenes) + " |")
    if published:
        lines += ["", "## The paper's Table II (published, not measured here)", "",
                  "GCGS paper, Table II: the same components switched off, on real DTU scans (3 views, mean "
                  "Chamfer over its test scans, mm), with MASt3R as the dense init and learned priors "
                  "(DSINE, Vis-MVSNet). Figures transcribed from the paper (`data/published/"
                  "gcgs_table2_ablation.csv`); they are on other scenes and another init than the rows above, "
                  "so compare each table's pattern, not cells across tables.", "",
                  *_header(["dense init (MASt3R)", "L_gcf", "L_nor", "mean (DTU, published)"])]
        lines += [f"| {_mark(p['dense_init'])} | {_mark(p['gcf'])} | {_mark(p['nor'])} | {p['mean_mm']:.2f} |"
                  for p in published]
    return "\n".join(lines) + "\n"


def csv_text(rows: list[dict], scenes: list[str]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    sides = [(k, s) for k in ("accuracy", "completeness") for s in (*scenes, "mean")]
    w.writerow(["row", *COMPONENTS, *scenes, "mean", *(f"{s}_covered" for s in scenes),
                *(f"{s}_{k}" for k, s in sides), "seeds", *(f"{s}_spread" for s in (*scenes, "mean"))])
    for r in rows:
        w.writerow([r["row"], *("" if r[k] is None else int(r[k]) for k in COMPONENTS),
                    *(f"{r[s]:.4f}" for s in scenes), f"{r['mean']:.4f}", *(f"{r['covered'][s]:.4f}" for s in scenes),
                    *(f"{r[k][s]:.4f}" for k, s in sides), r["seeds"],
                    *(f"{r['spread'][s]:.4f}" for s in (*scenes, "mean"))])
    return buf.getvalue()
