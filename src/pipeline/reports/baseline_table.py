"""The combined Markdown table of several scenes' baseline reports
(:func:`pipeline.runs.baseline.baseline_scene`)."""
from __future__ import annotations


def _fmt(x, nd=3) -> str:
    return "—" if x is None else f"{x:.{nd}f}"


def markdown(reports: dict[str, dict], notes: list[str] = ()) -> str:
    """The combined table of several scenes' reports (name -> report)."""
    commits = sorted({r.get("commit", "?") for r in reports.values()})
    machines = sorted({f"{r['cpu_cores']} CPU cores" if "cpu_cores" in r else "?" for r in reports.values()})
    lines = ["# Baseline: init point clouds and the classical MVS + TSDF mesh", "",
             f"Generated per scene by `gcgs baseline` (`reports/baseline/SCENE.json`; stage `baseline`) at commit "
             f"{', '.join(f'`{c}`' for c in commits)} on {'; '.join(machines)}, combined by `gcgs baseline-report`. "
             "All distances in mm (world frame). Definitions: `src/pipeline/evaluation/clouds.py`, "
             "`src/pipeline/runs/baseline.py` and docs/init.md.",
             "", "## Classical baseline mesh (mvs depth maps -> TSDF -> DTU Chamfer)", "",
             "| scene | accuracy | completeness | overall | triangles |", "| --- | --- | --- | --- | --- |"]
    for name, r in reports.items():
        m = r.get("evaluate", {}).get("metrics")
        kept = r.get("tsdf", {}).get("facts", {}).get("triangles_kept", "—")
        if m:
            lines.append(f"| {name} | {_fmt(m['accuracy_mm'])} | {_fmt(m['completeness_mm'])} | "
                         f"{_fmt(m['overall_mm'])} | {kept} |")
        elif "tsdf" in r:
            lines.append(f"| {name} | {'no GT' if r.get('gt') is None else r.get('evaluate', {}).get('status', '—')} "
                         f"| | | {kept} |")
    lines += ["", "## Init point clouds against the ground truth", "",
              "| scene | backend | points | median to GT surface | p90 | accuracy | completeness | "
              "precision@1mm | recall@1mm |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in reports.items():
        for b, e in r["backends"].items():
            c = e.get("cloud")
            if c:
                lines.append(f"| {name} | {b} | {c['points']} | {_fmt(c['median_to_surface_mm'])} | "
                             f"{_fmt(c['p90_to_surface_mm'])} | {_fmt(c['accuracy_mm'])} | {_fmt(c['completeness_mm'])} | "
                             f"{_fmt(c['precision_1mm'], 2)} | {_fmt(c['recall_1mm'], 2)} |")
            elif e.get("status", "ok") != "ok":
                lines.append(f"| {name} | {b} | {e['status']} | | | | | | |")
    lines += ["", "## Time and peak memory per step", "",
              "Each step is its own process: wall time, CPU time and peak resident memory (`VmHWM`) of the "
              "whole process, imports included (`pipeline.measure`). The default backend's figures are the init "
              "stage's own record (`init.json`: time inside the stage; no CPU time recorded there).", "",
              "| scene | step | wall s | CPU s | peak RSS MB |", "| --- | --- | --- | --- | --- |"]

    def row(name: str, label: str, run: dict) -> str:
        return (f"| {name} | {label} | {_fmt(run.get('wall_s'), 2)} | {_fmt(run.get('cpu_s'), 2)} | "
                f"{_fmt(run.get('peak_rss_mb'), 1)} |")

    for name, r in reports.items():
        for b, e in r["backends"].items():
            if "init" in e:
                lines.append(row(name, f"init {b}" + (" (init stage)" if "source" in e else ""), e["init"]))
        for key in ("tsdf", "evaluate"):
            if "run" in r.get(key, {}):
                lines.append(row(name, key, r[key]["run"]))
    lines += ["", "## Notes", ""] + [f"- {n}" for n in notes] + [""]
    return "\n".join(lines)
