"""``gcgs baseline``: the first measured baseline (docs/init.md).

For each scene: every init backend's point cloud, timed, and compared with the ground
truth (when the scene has one); then the classical baseline mesh -- ``mvs`` depth maps
fused by TSDF (``gcgs tsdf``) -- scored by ``gcgs evaluate`` (the role COLMAP plays in
the GCGS paper's Table I). Each step runs as its own process so that its wall time and
peak resident memory (``wait4``'s ``ru_maxrss``) are its own. Writes
``REPORT.json`` and ``REPORT.md``.

Point-cloud figures (world mm), for a cloud C and the GT:
* ``median_to_surface_mm``: median distance from C's points to the GT mesh surface
  (GT points when the folder has no mesh); the issue's "< 1 mm" criterion.
* ``accuracy_mm`` / ``completeness_mm``: the DTU-script means on the cloud as the data
  points (no mesh sampling, no mask culling): C in the observation mask -> GT points, and
  GT points above the ground plane -> C in the bounding box, each over distances below
  ``evaluate.max_dist_mm``.
* ``precision_1mm`` / ``recall_1mm``: fraction of C within 1 mm of the GT surface, and of
  GT points above the plane within 1 mm of C.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline import atomic
from pipeline.config import (
    EvaluateConfig,
    InitConfig,
    SceneEntry,
    from_dict,
    load_params,
    section,
)
from pipeline.evaluation import gt as gt_io
from pipeline.init.io import read_ply

BACKENDS = ("mvs", "sfm", "mast3r", "random")


# A small launcher forks and execs the step and reports the step's own rusage. Linux
# carries a process's pre-exec peak RSS across exec, so a step forked directly from this
# (large) process would report at least this process's size.
_LAUNCHER = """
import json, os, sys
pid = os.fork()
if pid == 0:
    os.execvp(sys.argv[2], sys.argv[2:])
_, status, ru = os.wait4(pid, 0)
with open(sys.argv[1], "w") as fh:
    json.dump({"rc": os.waitstatus_to_exitcode(status), "maxrss_kb": ru.ru_maxrss,
               "cpu_s": ru.ru_utime + ru.ru_stime}, fh)
"""


def run_timed(cmd: list[str]) -> dict:
    """Run ``cmd``; return its exit code, output, wall seconds, CPU seconds and peak RSS (MB)."""
    import tempfile

    fd, stats_path = tempfile.mkstemp(suffix=".json")
    os.close(fd)
    try:
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", _LAUNCHER, stats_path, *cmd], stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True)
        wall = time.perf_counter() - t0
        text = Path(stats_path).read_text()
        stats = json.loads(text) if text else {}  # empty: the launcher itself failed
    finally:
        Path(stats_path).unlink(missing_ok=True)
    return {"cmd": " ".join(cmd), "rc": stats.get("rc", proc.returncode), "output": proc.stdout[-4000:],
            "wall_s": round(wall, 2), "peak_rss_mb": round(stats.get("maxrss_kb", 0) / 1024.0, 1),
            "cpu_s": round(stats.get("cpu_s", 0.0), 2)}


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unsigned distance (mm) of points to a triangle mesh (Open3D ray-casting scene)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)


def cloud_metrics(points: np.ndarray, ground: gt_io.GroundTruth, cfg: EvaluateConfig) -> dict:
    """Figures of a point cloud against the GT (module docstring)."""
    mesh_path = ground.root / "mesh.ply"
    if mesh_path.is_file():
        V, F = gt_io.read_mesh(mesh_path)
        d_surf = distance_to_mesh(points, V, F)
        surface = "GT mesh"
    else:
        d_surf, _ = cKDTree(ground.points_mm).query(points)
        surface = "GT points"
    inbound, in_obs = ground.box_and_observed(points, cfg.patch_mm)
    data_in = points[inbound]
    d_acc, _ = cKDTree(ground.points_mm).query(data_in[in_obs], distance_upper_bound=cfg.max_dist_mm)
    gt_above = ground.points_mm[ground.above_plane(ground.points_mm)]
    if len(data_in):
        d_comp, _ = cKDTree(data_in).query(gt_above, distance_upper_bound=cfg.max_dist_mm)
    else:
        d_comp = np.full(len(gt_above), np.inf)

    def mean_below(d):
        d = d[d < cfg.max_dist_mm]
        return float(d.mean()) if len(d) else None

    acc, comp = mean_below(d_acc), mean_below(d_comp)
    return {
        "points": int(len(points)),
        "median_to_surface_mm": float(np.median(d_surf)),
        "p90_to_surface_mm": float(np.percentile(d_surf, 90)),
        "surface": surface,
        "accuracy_mm": acc,
        "completeness_mm": comp,
        "overall_mm": (acc + comp) / 2 if acc is not None and comp is not None else None,
        "precision_1mm": float(np.mean(d_surf < 1.0)),
        "recall_1mm": float(np.mean(d_comp < 1.0)),
    }


def baseline_scene(name: str, entry: SceneEntry, scene_dir: Path, work: Path, mast3r_model: str | None,
                   eval_cfg: EvaluateConfig, params_path: str | None, log) -> dict:
    if not scene_dir.is_dir():
        raise FileNotFoundError(f"{scene_dir}: prepared scene not found (run `dvc repro prepare@{name}`)")
    ground = gt_io.read_ground_truth(entry.gt) if entry.gt else None
    extra = ["--params", params_path] if params_path else []
    result: dict = {"scene": str(scene_dir), "gt": entry.gt, "backends": {}}
    for backend in BACKENDS:
        out_dir = work / name / f"init_{backend}"
        if backend == "mast3r" and not mast3r_model:
            result["backends"][backend] = {"status": "not run: no MASt3R ONNX model file (weights cannot be "
                                                     "downloaded here; see docs/init.md for the export script)"}
            continue
        cmd = ["gcgs", "init", "--scene", str(scene_dir), "--backend", backend, "--out-dir", str(out_dir), *extra]
        if backend == "mast3r":
            cmd += ["--model", mast3r_model]
        run = run_timed(cmd)
        entry_out = {"status": "ok" if run["rc"] == 0 else "failed", "init": run}
        if run["rc"] == 0:
            info = json.loads((out_dir / "init.json").read_text())
            entry_out["init_facts"] = {k: v for k, v in info.items() if k not in ("config", "scene")}
            if ground is not None:
                entry_out["cloud"] = cloud_metrics(read_ply(out_dir / "points.ply").points_mm, ground, eval_cfg)
        log(f"[baseline] {name} {backend}: {entry_out['status']} in {run['wall_s']} s, {run['peak_rss_mb']} MB"
            + (f", median {entry_out['cloud']['median_to_surface_mm']:.3f} mm" if "cloud" in entry_out else ""))
        result["backends"][backend] = entry_out

    if result["backends"]["mvs"].get("status") == "ok":
        mesh = work / name / "mvs_tsdf.ply"
        run = run_timed(["gcgs", "tsdf", "--init-dir", str(work / name / "init_mvs"), "--scene", str(scene_dir),
                         "--out", str(mesh)])
        result["tsdf"] = {"status": "ok" if run["rc"] == 0 else "failed", "run": run}
        if run["rc"] == 0:
            result["tsdf"]["facts"] = json.loads(run["output"].strip().splitlines()[-1])
            if ground is not None:
                metrics_path = work / name / "mvs_tsdf_metrics.json"
                ev = run_timed(["gcgs", "evaluate", "--mesh", str(mesh), "--scene", str(scene_dir), "--gt",
                                str(entry.gt), "--out", str(metrics_path), *extra])
                result["evaluate"] = {"status": "ok" if ev["rc"] == 0 else "failed", "run": ev}
                if ev["rc"] == 0:
                    m = json.loads(metrics_path.read_text())
                    result["evaluate"]["metrics"] = {k: m[k] for k in ("accuracy_mm", "completeness_mm", "overall_mm",
                                                                       "valid", "problems", "counts")}
        log(f"[baseline] {name} tsdf+evaluate: {result['tsdf']['status']}"
            + (f", overall {result['evaluate']['metrics']['overall_mm']}" if "metrics" in result.get("evaluate", {}) else ""))
    return result


def _fmt(x, nd=3):
    return "—" if x is None else f"{x:.{nd}f}"


def write_markdown(path: Path, report: dict) -> None:
    lines = ["# Baseline: init point clouds and the classical MVS + TSDF mesh", "",
             f"Generated by `gcgs baseline` at commit `{report['commit']}` on {report['machine']}. "
             "All distances in mm (world frame). Definitions: `src/pipeline/stages/baseline.py` and docs/init.md.",
             "", "## Classical baseline mesh (mvs depth maps -> TSDF -> `gcgs evaluate`)", "",
             "| scene | accuracy | completeness | overall | triangles |", "| --- | --- | --- | --- | --- |"]
    for name, r in report["scenes"].items():
        m = r.get("evaluate", {}).get("metrics")
        if m:
            lines.append(f"| {name} | {_fmt(m['accuracy_mm'])} | {_fmt(m['completeness_mm'])} | "
                         f"{_fmt(m['overall_mm'])} | {r['tsdf']['facts']['triangles_kept']} |")
        elif "tsdf" in r:
            lines.append(f"| {name} | no GT | | | {r['tsdf'].get('facts', {}).get('triangles_kept', '—')} |")
    lines += ["", "## Init point clouds against the ground truth", "",
              "| scene | backend | points | median to GT surface | p90 | accuracy | completeness | "
              "precision@1mm | recall@1mm |", "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, r in report["scenes"].items():
        for b, e in r["backends"].items():
            c = e.get("cloud")
            if c:
                lines.append(f"| {name} | {b} | {c['points']} | {_fmt(c['median_to_surface_mm'])} | "
                             f"{_fmt(c['p90_to_surface_mm'])} | {_fmt(c['accuracy_mm'])} | {_fmt(c['completeness_mm'])} | "
                             f"{_fmt(c['precision_1mm'], 2)} | {_fmt(c['recall_1mm'], 2)} |")
            elif e.get("status", "").startswith("not run"):
                lines.append(f"| {name} | {b} | {e['status']} | | | | | | |")
    lines += ["", "## Time and peak memory per step (each its own process)", "",
              "| scene | step | wall s | CPU s | peak RSS MB |", "| --- | --- | --- | --- | --- |"]
    for name, r in report["scenes"].items():
        for b, e in r["backends"].items():
            if "init" in e:
                i = e["init"]
                lines.append(f"| {name} | init {b} | {i['wall_s']} | {i['cpu_s']} | {i['peak_rss_mb']} |")
        for key, label in (("tsdf", "tsdf"), ("evaluate", "evaluate")):
            if key in r and "run" in r[key]:
                i = r[key]["run"]
                lines.append(f"| {name} | {label} | {i['wall_s']} | {i['cpu_s']} | {i['peak_rss_mb']} |")
    lines += ["", "## Notes", ""] + [f"- {n}" for n in report["notes"]] + [""]
    atomic.write_text(path, "\n".join(lines))


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenes", nargs="+", default=None, help="scene names (default: every scene in params `scenes`)")
    p.add_argument("--scenes-root", default="data/scenes", help="folder of the prepared scenes")
    p.add_argument("--work", default="data/baseline", help="folder for the clouds, meshes and metrics")
    p.add_argument("--report", default="reports/baseline", help="writes REPORT.json and REPORT.md")
    p.add_argument("--mast3r-model", default=None, help="MASt3R ONNX file (default: init.mast3r.model)")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")
    p.add_argument("--note", action="append", default=[], help="a line for the report's notes")


def run(args: argparse.Namespace) -> int:
    params = load_params(args.params)
    eval_cfg = section(EvaluateConfig, "evaluate", params)
    init_cfg = section(InitConfig, "init", params)
    scenes = {k: from_dict(SceneEntry, v, where=f"scenes.{k}") for k, v in (params.get("scenes") or {}).items()}
    names = args.scenes or list(scenes)
    unknown = [n for n in names if n not in scenes]
    if unknown:
        raise ValueError(f"scene(s) {unknown} not in params `scenes` ({sorted(scenes)})")
    work = Path(args.work)
    log = lambda m: print(m, flush=True)  # noqa: E731
    report = {
        "commit": subprocess.run(["git", "describe", "--always", "--dirty"], capture_output=True, text=True).stdout.strip(),
        "machine": f"{os.cpu_count()} CPU cores, no GPU",
        "init_config": params.get("init"),
        "evaluate_config": params.get("evaluate"),
        "scenes": {},
        "notes": list(args.note),
    }
    for name in names:
        report["scenes"][name] = baseline_scene(name, scenes[name], Path(args.scenes_root) / name, work, args.mast3r_model or init_cfg.mast3r.model,
                                                eval_cfg, args.params, log)
    out = Path(args.report)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out.with_suffix(".json"), json.dumps(report, indent=2) + "\n")
    write_markdown(out.with_suffix(".md"), report)
    log(f"[baseline] wrote {out.with_suffix('.json')} and {out.with_suffix('.md')}")
    return 0 if all(e.get("status") != "failed" for r in report["scenes"].values() for e in r["backends"].values()) else 1

