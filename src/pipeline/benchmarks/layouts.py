"""``gcgs bench-layouts``: one synthetic scene prepared from each layout `gcgs prepare` reads
(DTU NeuS/IDR, COLMAP, nerfstudio) and trained with the default params: does it give the
same Chamfer distance? (docs/inputs.md, "Same scene, three layouts".)

For each scene ``S`` the DTU-layout scan ``data/synth/S`` is exported
(:mod:`pipeline.data.export`) to a COLMAP folder (binary model) and a nerfstudio folder under
``WORK/S/``. The COLMAP model's ``points3D`` stand in for structure-from-motion points:
``--points`` ground-truth points (``data/synth/S/gt``) that at least two of the scan's
cameras see (inside the image, not hidden behind the GT mesh). Each layout then runs the
per-scene pipeline as ``dvc repro`` does (the library functions of the stages, with the
params of ``--params``): prepare, init, priors, optimize, mesh, into ``WORK/S/LAYOUT/``, in a
fresh child process per layout (its wall time and peak memory its own), and the mesh is
scored like ``gcgs evaluate --scene data/scenes/S --gt data/synth/S/gt`` (culled by the
DTU-layout scene's masks; all layouts' meshes are in the scan's world frame, mm).

``--sphere dtu`` prepares the COLMAP and nerfstudio layouts with the DTU layout's unit
sphere (``gcgs prepare --sphere``) instead of the one they derive from the cameras, so the
layouts differ only in the cameras: the skew they cannot hold (dropped) and their files'
rounding, ~1e-4 px together. ``--skew-free`` adds a run of the DTU layout with the skew
dropped too (``dtu_noskew``). ``--perturb-runs N``
adds N runs of the DTU layout whose cameras are shifted on the image by ``--perturb-px``
(a random direction per camera and run; :func:`perturbed_scan`): the spread of those runs is
how far the same pipeline moves under a camera change of that size, the yardstick for the
layouts' differences (a training seed moves other things: the random init of colours and
the densification's samples).

Also recorded: the largest reprojection difference (px, at the training size) of the
prepared cameras against the DTU-layout prepared scene ``data/scenes/S`` over every camera
and the sparse points, and each layout's unit sphere (``scale_mat``: centre and radius in
mm), which sets what every normalised-unit setting (``mesh.voxel_norm``,
``init.voxel_norm``, ``optimize.scene_extent`` ...) means in mm. One CSV row per scene and
layout.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from pipeline import atomic, geometry
from pipeline.data import dtu, export
from pipeline.measure import provenance, run_in_child
from pipeline.raycast import MeshCaster

LAYOUTS = ("dtu", "colmap", "nerfstudio")
SCENES = ("synth_thin", "synth_relief", "synth_textureless")
COLUMNS = ("scene", "layout", "sphere_from", "overall_mm", "accuracy_mm", "completeness_mm", "max_reprojection_px",
           "sphere_cx_mm", "sphere_cy_mm", "sphere_cz_mm", "sphere_radius_mm", "radius_vs_dtu",
           "init_points", "surfels_final", "train_wall_s", "pipeline_wall_s", "eval_wall_s", "peak_rss_mb")


def seen_points(points_world: np.ndarray, K: Mapping[int, np.ndarray], world_to_cam: Mapping[int, np.ndarray],
                size: tuple[int, int], n: int, min_views: int = 2, mesh: tuple[np.ndarray, np.ndarray] | None = None,
                seed: int = 0) -> np.ndarray:
    """Up to ``n`` of ``points_world`` (a random subset, ``seed``) that at least ``min_views``
    cameras see: in front of the camera, inside its ``size`` image and, with ``mesh``
    (vertices, triangles; world units), not hidden behind it. A stand-in for the sparse
    points of structure from motion on a synthetic scene whose surface is known."""
    pts = np.asarray(points_world, np.float64).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    cand = pts[rng.permutation(len(pts))[: min(len(pts), 20 * n)]]
    caster = None
    if mesh is not None:
        caster = MeshCaster(*mesh)
    W, H = size
    count = np.zeros(len(cand), int)
    for v in sorted(K):
        px, z = geometry.project(K[v], world_to_cam[v], cand)
        ok = (z > 0) & np.all(px >= -0.5, 1) & (px[:, 0] < W - 0.5) & (px[:, 1] < H - 0.5)
        if caster is not None and ok.any():
            centre = geometry.camera_center(world_to_cam[v])
            d = cand[ok] - centre
            # a ray to just short of the point: blocked when another surface lies in between
            rays = np.concatenate([np.broadcast_to(centre, d.shape), d * (1.0 - 1e-3)], 1)
            hidden = caster.occluded(rays)
            idx = np.flatnonzero(ok)
            ok[idx[hidden]] = False
        count += ok
    return cand[count >= min_views][:n]


def export_layouts(name: str, synth_dir: Path, work: Path, n_points: int, seed: int = 0) -> tuple[dict, np.ndarray]:
    """The scan ``synth_dir`` as each layout's source folder (``{layout: folder}``) and the
    sparse points written into the COLMAP model (also the reprojection check's points)."""
    from pipeline.evaluation import gt

    cams = dtu.load_cameras(synth_dir)
    size = dtu.stored_image_size(synth_dir)
    scan_id = dtu.read_meta(synth_dir).get("scan_id")
    ground = gt.read_ground_truth(synth_dir / "gt", scan_id)
    mesh_path = ground.root / "mesh.ply"
    mesh = gt.read_mesh(mesh_path) if mesh_path.is_file() else None
    ids = dtu.image_ids(synth_dir)
    points = seen_points(ground.points_mm, {v: cams.K[v] for v in ids},
                                {v: cams.world_to_cam[v] for v in ids}, size, n_points, mesh=mesh, seed=seed)
    srcs = {"dtu": synth_dir, "colmap": work / name / "src_colmap", "nerfstudio": work / name / "src_nerfstudio"}
    export.export_colmap(synth_dir, srcs["colmap"], binary=True, points_world=points)
    export.export_nerfstudio(synth_dir, srcs["nerfstudio"])
    return srcs, points


def perturbed_scan(synth_dir: Path, out: Path, shift_px: float, seed: int, drop_skew: bool = False) -> Path:
    """A copy of the DTU-layout scan ``synth_dir`` at ``out`` whose every camera projects
    ``shift_px`` pixels away from the original, in a random direction per camera
    (``seed``): ``world_mat_i <- A world_mat_i`` with ``A`` the image translation by that
    shift, so points, depths and the unit sphere are untouched. ``drop_skew`` first sets
    each camera's skew ``K[0, 1]`` to 0, the one change the COLMAP and nerfstudio layouts
    make to these cameras (:mod:`pipeline.data.export`). Images, masks and the scan's
    metadata are symlinked, not copied; ``out`` is replaced like any folder gcgs writes
    (:func:`pipeline.atomic.atomic_dir`), never a folder it did not write."""
    synth_dir = Path(synth_dir).resolve()
    cams = np.load(dtu.find_camera_file(synth_dir))
    rng = np.random.default_rng(seed)
    shifted = {}
    for key in cams.files:
        P = np.asarray(cams[key], np.float64)
        if key.startswith("world_mat_"):
            if drop_skew:
                K, world_to_cam = geometry.decompose_projection(P[:3])
                K[0, 1] = 0.0
                P = np.eye(4)
                P[:3] = K @ world_to_cam[:3]
            angle = rng.uniform(0.0, 2.0 * np.pi)
            A = np.eye(P.shape[0])
            A[0, 2], A[1, 2] = shift_px * np.cos(angle), shift_px * np.sin(angle)
            P = A @ P
        shifted[key] = P
    with atomic.atomic_dir(out, export.KIND, inputs=(synth_dir,)) as tmp:
        for entry in synth_dir.iterdir():
            if entry.name != "cameras_sphere.npz":
                (tmp / entry.name).symlink_to(entry)
        np.savez(tmp / "cameras_sphere.npz", **shifted)
    return Path(out)


def run_layout(src: str, out: str, name: str, ref_scene: str, gt_dir: str, params_path: str | None,
               sphere: tuple[float, float, float, float] | None = None) -> dict:
    """The per-scene pipeline on ``src`` into ``out`` (scene/, init/, priors/, surfels/,
    mesh/, eval.json) with the params of ``params_path``, as the dvc stages run it; the
    mesh is scored against ``gt_dir`` culled by ``ref_scene``'s masks (the DTU-layout
    prepared scene). ``sphere`` (cx, cy, cz, radius; world units) replaces the layout's unit
    sphere, as ``gcgs prepare --sphere`` does. Runs in a child process
    (:func:`pipeline.measure.run_in_child`)."""
    from pipeline.config.ablation import losses_in_use
    from pipeline.config.data import DataConfig
    from pipeline.config.evaluate import EvaluateConfig
    from pipeline.config.init import InitConfig
    from pipeline.config.loss import LossConfig
    from pipeline.config.mesh import MeshConfig
    from pipeline.config.optimize import OptimizeConfig
    from pipeline.config.params import load_params, section
    from pipeline.config.priors import PriorsConfig
    from pipeline.data.prepare import prepare_scene
    from pipeline.evaluation import dtu_eval, gt, seen
    from pipeline.measure import measure
    from pipeline.rasterizer import resolve_backend
    from pipeline.runs.init import run_init
    from pipeline.runs.mesh import mesh_surfels_dir
    from pipeline.runs.optimize import run_optimize
    from pipeline.runs.priors import run_priors

    params = load_params(params_path)
    out_dir = Path(out)
    d = {k: out_dir / k for k in ("scene", "init", "priors", "surfels", "mesh")}
    views = section(DataConfig, "data", params).views
    t0 = time.perf_counter()
    prepare_scene(src, d["scene"], section(DataConfig, "data", params), name=name, sphere=sphere)
    _, init_info = run_init(d["scene"], d["init"], section(InitConfig, "init", params))
    run_priors(d["scene"], d["priors"], section(PriorsConfig, "priors", params), losses_in_use(params),
               init_dir=d["init"])
    opt = section(OptimizeConfig, "optimize", params)
    with measure(reset_peak=False) as train:
        result = run_optimize(d["scene"], d["init"], d["priors"], d["surfels"], opt, section(LossConfig, "loss", params),
                              checkpoint=out_dir / ".surfels.ckpt.pt", live_dir=None, progress=False)
    mesh_info = mesh_surfels_dir(d["scene"], d["surfels"], d["mesh"], section(MeshConfig, "mesh", params),
                                 resolve_backend(opt.backend), init_dir=d["init"])
    pipeline_wall = time.perf_counter() - t0

    t1 = time.perf_counter()
    cfg = section(EvaluateConfig, "evaluate", params)
    ground = gt.read_ground_truth(gt_dir, dtu.read_meta(Path(ref_scene)).get("scan_id"))
    vertices, triangles = gt.read_mesh(d["mesh"] / "mesh.ply")
    metrics = dtu_eval.evaluate_mesh(vertices, triangles, ground, cfg,
                                     views=dtu_eval.load_cull_views(ref_scene, cfg.cull_views, views), seed=0,
                                     log=None, name=str(d["mesh"] / "mesh.ply"),
                                     seen_views=seen.load_input_views(ref_scene, views))
    metrics.update(mesh=str(d["mesh"] / "mesh.ply"), scene=str(ref_scene), gt=str(ground.root))
    dtu_eval.write_metrics(out_dir / "eval.json", metrics)
    return {"metrics": metrics, "init_points": init_info["num_points"], "surfels_final": result.params.num,
            # a run resumed from its checkpoint counts the training time spent before it too
            "mesh": mesh_info, "train_wall_s": round(train.wall_s + result.spent_before["wall_s"], 2),
            "pipeline_wall_s": round(pipeline_wall + result.spent_before["wall_s"], 2),
            "eval_wall_s": round(time.perf_counter() - t1, 2)}


def max_reprojection_px(scene_dir: Path, ref_dir: Path, points: np.ndarray) -> float:
    """Largest pixel distance between ``points`` projected by the cameras of ``scene_dir``
    and by those of ``ref_dir`` (every camera both have; an error when the sets differ)."""
    cams, ref = dtu.load_cameras(scene_dir), dtu.load_cameras(ref_dir)
    if cams.ids != ref.ids:
        raise ValueError(f"{scene_dir}: cameras {cams.ids[:5]}... differ from {ref_dir}'s {ref.ids[:5]}...")
    worst = 0.0
    for v in ref.ids:
        a, _ = geometry.project(cams.K[v], cams.world_to_cam[v], points)
        b, _ = geometry.project(ref.K[v], ref.world_to_cam[v], points)
        worst = max(worst, float(np.max(np.linalg.norm(a - b, axis=1))))
    return worst


def row(scene: str, layout: str, sphere_from: str, run: dict, reproj: float, sphere: np.ndarray,
        ref_radius: float, usage_peak: float | None) -> dict:
    m = run["metrics"]
    return {"scene": scene, "layout": layout, "sphere_from": sphere_from, "overall_mm": f"{m['overall_mm']:.4f}",
            "accuracy_mm": f"{m['accuracy_mm']:.4f}", "completeness_mm": f"{m['completeness_mm']:.4f}",
            "max_reprojection_px": f"{reproj:.2e}",
            "sphere_cx_mm": f"{sphere[0, 3]:.2f}", "sphere_cy_mm": f"{sphere[1, 3]:.2f}",
            "sphere_cz_mm": f"{sphere[2, 3]:.2f}", "sphere_radius_mm": f"{sphere[0, 0]:.2f}",
            "radius_vs_dtu": f"{sphere[0, 0] / ref_radius:.3f}", "init_points": run["init_points"],
            "surfels_final": run["surfels_final"], "train_wall_s": run["train_wall_s"],
            "pipeline_wall_s": run["pipeline_wall_s"], "eval_wall_s": run["eval_wall_s"],
            "peak_rss_mb": usage_peak}


def write_csv(path: Path, rows: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    atomic.write_text(path, buf.getvalue())


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenes", nargs="+", default=list(SCENES), help="synthetic scenes (data/synth/S, data/scenes/S)")
    p.add_argument("--layouts", nargs="+", choices=LAYOUTS, default=list(LAYOUTS), help="layouts to run")
    p.add_argument("--work-dir", required=True, help="where the exported captures and every run's outputs go "
                   "(WORK/S/src_colmap, WORK/S/LAYOUT/...); a run's folders are replaced when rerun")
    p.add_argument("--out", required=True, help="CSV to write (one row per scene and layout)")
    p.add_argument("--synth-root", default="data/synth", help="folder of the DTU-layout synthetic scans (and gt/)")
    p.add_argument("--scenes-root", default="data/scenes", help="folder of the DTU-layout prepared scenes "
                   "(reference cameras, culling masks)")
    p.add_argument("--points", type=int, default=3000, help="sparse points written into the COLMAP model")
    p.add_argument("--params", default=None, help="params.yaml (default: ./params.yaml)")
    p.add_argument("--sphere", choices=("derived", "dtu"), default="derived",
                   help="the COLMAP and nerfstudio layouts' unit sphere: the one they derive (default), or the "
                   "DTU layout's, given as `gcgs prepare --sphere` does")
    p.add_argument("--perturb-runs", type=int, default=0, help="runs of the DTU layout with every camera shifted "
                   "by --perturb-px in a random direction (layouts dtu_shift1..N): the spread such a change causes")
    p.add_argument("--perturb-px", type=float, default=1e-4, help="the shift of the perturbed runs, px at the "
                   "scan's stored size (the layouts' cameras differ by ~1e-4 px)")
    p.add_argument("--skew-free", action="store_true", help="also run the DTU layout with every camera's skew "
                   "set to 0 (layout dtu_noskew), the change the COLMAP and nerfstudio layouts make")
    p.add_argument("--resume", action="store_true", help="keep the runs of WORK that finished (their run.json) "
                   "instead of running them again (the exports are redone)")


def run(args: argparse.Namespace) -> int:
    work, out = Path(args.work_dir), Path(args.out)
    atomic.check_output_file(out)
    rows: list[dict] = []
    if args.perturb_runs < 0 or not (np.isfinite(args.perturb_px) and args.perturb_px > 0):
        raise SystemExit("gcgs bench-layouts: --perturb-runs must be >= 0 and --perturb-px a positive number")
    for scene in args.scenes:
        synth_dir, ref_scene = Path(args.synth_root) / scene, Path(args.scenes_root) / scene
        print(f"[bench-layouts] {scene}: exporting {synth_dir} to COLMAP (binary) and nerfstudio ...", flush=True)
        srcs, points = export_layouts(scene, synth_dir, work, args.points)
        ref_norm_to_world = dtu.load_cameras(ref_scene).norm_to_world
        ref_radius = ref_norm_to_world[0, 0]
        dtu_sphere = (*map(float, ref_norm_to_world[:3, 3]), float(ref_radius))
        runs = [(layout, srcs[layout], dtu_sphere if args.sphere == "dtu" and layout != "dtu" else None)
                for layout in args.layouts]
        for k in range(1, args.perturb_runs + 1):
            shifted = perturbed_scan(synth_dir, work / scene / f"src_dtu_shift{k}", args.perturb_px, seed=k)
            runs.append((f"dtu_shift{k}", shifted, None))
        if args.skew_free:
            runs.append(("dtu_noskew", perturbed_scan(synth_dir, work / scene / "src_dtu_noskew", 0.0, seed=0,
                                                      drop_skew=True), None))
        for layout, src, sphere in runs:
            sphere_from = "dtu" if layout.startswith("dtu") or sphere is not None else "derived"
            out_dir = work / scene / layout
            if args.resume and (out_dir / "run.json").is_file():
                rows.append(json.loads((out_dir / "run.json").read_text())["row"])
                print(f"[bench-layouts] {scene} / {layout}: kept the finished run in {out_dir}", flush=True)
                write_csv(out, rows)
                continue
            print(f"[bench-layouts] {scene} / {layout}: prepare, init, priors, optimize, mesh, evaluate ...", flush=True)
            (out_dir / "run.json").unlink(missing_ok=True)
            res, usage = run_in_child(run_layout, str(src), str(out_dir), scene, str(ref_scene),
                                      str(synth_dir / "gt"), args.params, sphere)
            reproj = max_reprojection_px(out_dir / "scene", ref_scene, points)
            norm_to_world = dtu.load_cameras(out_dir / "scene").norm_to_world
            rows.append(row(scene, layout, sphere_from, res, reproj, norm_to_world, ref_radius, usage.peak_rss_mb))
            atomic.write_text(out_dir / "run.json", json.dumps({"row": rows[-1], **res, "max_reprojection_px": reproj,
                                                                "child_wall_s": round(usage.wall_s, 2)},
                                                               indent=2, default=str) + "\n")
            print(f"[bench-layouts] {scene} / {layout}: " + ", ".join(f"{k} {rows[-1][k]}" for k in COLUMNS[2:]),
                  flush=True)
            write_csv(out, rows)  # after every run: a long benchmark keeps what it has
    facts = provenance()
    print(f"[bench-layouts] wrote {out} ({len(rows)} rows; commit {facts['commit']}, {facts['cpu_cores']} cores, "
          f"load {facts['load_average_1min']})")
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="gcgs bench-layouts", description=__doc__.split("\n")[0])
    add_arguments(p)
    return run(p.parse_args(argv))
