"""``reports/index.md``: one page a person reads to see what was measured, on what data, with
which settings and commit. It embeds the tables that exist (Table I, Table II), the
speed-accuracy plot, each scene's figures, settings and picture, and links each scene's
training curves. Every path in it is relative to the reports folder."""
from __future__ import annotations

import re
from pathlib import Path

from pipeline.errors import MissingInputError
from pipeline.evaluation.record import SceneMetrics

# What may exist, in the order shown: (file under reports/, title). Table I is required.
TABLES = (("table1.md", "Table I"), ("table2.md", "Table II: ablation"))
SPEED_PLOT = "speed_accuracy.png"
SPEED_TABLE = "speed_accuracy.csv"


def _embedded(text: str) -> str:
    """A Markdown document shown inside another: its headings one level deeper."""
    return re.sub(r"(?m)^(#{1,5}) ", r"#\1 ", text.strip())


def _fmt(value, nd: int) -> str:
    return "" if value is None else f"{value:.{nd}f}"


def scene_section(name: str, entry: dict, metrics: SceneMetrics, reports: Path) -> list[str]:
    """Figures, settings, picture and training curves of one scene."""
    train, timing = metrics.train, metrics.timing
    gt = (entry or {}).get("gt")
    lines = [f"### {name}", "",
             f"Source `{(entry or {}).get('src', '?')}`; ground truth: {f'`{gt}`' if gt else 'none'}. "
             f"Trained with preset **{train.get('preset', '?')}**, {train.get('iterations', '?')} iterations on the "
             f"{train.get('backend', '?')} backend, {train.get('surfels_final', '?')} surfels at the end; training "
             f"took {_fmt(timing.get('wall_s'), 0)} s wall, {_fmt(timing.get('cpu_s'), 0)} s CPU, peak "
             f"{_fmt(timing.get('peak_rss_mb'), 0)} MB (`metrics/{name}.json`).", ""]
    if metrics.chamfer is not None:
        c = metrics.chamfer
        lines += ["| Chamfer of the mesh against the GT (mm) | value |", "| --- | ---: |",
                  f"| accuracy (mesh -> GT, mean) | {_fmt(c.accuracy_mm, 3)} |",
                  f"| completeness (GT -> mesh, mean) | {_fmt(c.completeness_mm, 3)} |",
                  f"| overall = (accuracy + completeness) / 2 | {_fmt(c.overall_mm, 3)} |"]
        for split, key, what, share in ((c.accuracy_by_views_seen, "accuracy_mm", "accuracy on surface", "the mesh"),
                                        (c.completeness_by_views_seen, "completeness_mm", "completeness on GT surface",
                                         "the GT points")):
            for group, label in (("2+", "seen by >= 2 input views"), ("1", "seen by 1 input view"),
                                 ("0", "seen by none")):
                r = (split or {}).get(group)
                if r is not None:
                    lines.append(f"| {what} {label} ({100 * r['fraction']:.1f}% of {share}) | {_fmt(r[key], 3)} |")
        e = metrics.input_depth_error
        if e is not None:
            lines.append(f"| depth the mesh is fused from, at the input views, against the GT's: median abs error "
                         f"(signed median; share above 1 mm) | {_fmt(e.get('median_abs_mm'), 3)} "
                         f"({_fmt(e.get('signed_median_mm'), 3)}; {_fmt(e.get('share_above_1mm'), 2)}) |")
            if e.get("outliers") is not None:
                lines.append(f"| pixels off by more than 5 mm (of them in front of the truth; their share of the "
                             f"summed absolute error) | {_fmt(e.get('outliers'), 3)} ({_fmt(e.get('outliers_in_front'), 3)}; "
                             f"{_fmt(e.get('outlier_error_share'), 2)}) |")
        lines.append("")
        if not c.valid:
            lines += [f"Evaluation flagged invalid: {'; '.join(c.problems)}", ""]
    if metrics.heldout is not None:
        h = metrics.heldout
        lines += [f"| held-out views ({h.views} views not used in training, "
                  f"{'x'.join(map(str, h.size))} px) | value |", "| --- | ---: |",
                  f"| mask IoU of the mesh's silhouette | {_fmt(h.mesh_iou_mean, 3)} |",
                  f"| mask IoU of the surfels (alpha > 0.5) | {_fmt(h.iou_mean, 3)} |",
                  f"| mask IoU of the visual hull of the input masks (reference) | {_fmt(h.hull_iou_mean, 3)} |",
                  f"| PSNR over the mask (dB) | {_fmt(h.psnr_masked_db_mean, 2)} |", ""]
    pictures = (
        ("", "input view, rendered colour, rendered normal, mesh",
         "Left to right, at the first input view: the input image, the trained surfels' rendered colour and normals "
         "(camera frame, (n + 1) / 2 with x right, y up, z to the viewer), the extracted mesh lit from the camera."),
        ("_heldout", "mesh silhouette over held-out masks",
         "Held-out views, the mesh's silhouette over each view's mask on the dimmed image: grey where both cover a "
         "pixel, red where only the mask does (missed), blue where only the mesh does (extra); the IoU printed is "
         "the mesh's."),
    )
    for suffix, alt, caption in pictures:
        if (reports / "renders" / f"{name}{suffix}.png").is_file():
            lines += [f"![{name}: {alt}](renders/{name}{suffix}.png)", "", caption, ""]
    curves = sorted((reports / "train" / name / "plots" / "metrics" / "train").glob("*.tsv"))
    if curves:
        links = ", ".join(f"[{c.stem}]({c.relative_to(reports).as_posix()})" for c in curves)
        lines += [f"Training curves (dvclive, per step): {links}; all as plots: `dvc plots show` "
                  f"(dvc.yaml `plots` of stage `optimize@{name}`).", ""]
    return lines


def index_markdown(reports_dir: str | Path, scenes: dict[str, dict], commit: str) -> str:
    """The report page for the configured ``scenes`` (params ``scenes``); every scene needs
    ``reports_dir/metrics/NAME.json`` and ``reports_dir/table1.md`` must exist."""
    reports = Path(reports_dir)
    metrics = {n: SceneMetrics.read(reports / "metrics" / f"{n}.json", "run the score stage") for n in scenes}
    if not (reports / "table1.md").is_file():
        raise MissingInputError(f"{reports / 'table1.md'}: Table I not found (run `gcgs table1`)")
    lines = ["# Results", "",
             f"Generated by `gcgs report-index` (DVC stage `report-index`) at commit `{commit}` from the files in "
             "this folder; each section names the file its numbers come from. Distances are world millimetres. "
             "Every scene is reconstructed from 3 input views with known cameras.", "",
             "Contents: " + ", ".join(f"[{t}]({f})" for f, t in TABLES if (reports / f).is_file())
             + (f", [speed-accuracy plot]({SPEED_PLOT})" if (reports / SPEED_PLOT).is_file() else "")
             + ", [scenes](#scenes)", ""]
    for file, title in TABLES:
        if (reports / file).is_file():
            head, _, body = _embedded((reports / file).read_text()).partition("\n")
            lines += [head, "", f"(the file [`{file}`]({file}))", body, ""]
    if (reports / SPEED_PLOT).is_file():
        lines += ["## Speed-accuracy trade", "",
                  f"![time against overall Chamfer, Pareto front marked]({SPEED_PLOT})", "",
                  f"Each point is one measured setting (`{SPEED_TABLE}`)." if (reports / SPEED_TABLE).is_file()
                  else "", ""]
    lines += ["## Scenes", ""]
    for name, entry in scenes.items():
        lines += scene_section(name, entry, metrics[name], reports)
    return "\n".join(lines).rstrip() + "\n"
