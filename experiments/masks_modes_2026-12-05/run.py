"""Masks given / derived / none on the synthetic scenes (issue 58's table).

Each scene (a key of params ``scenes``: the synthetic suite and scan24) is prepared three ways from the same source and run through the
same stages as a user would (``gcgs`` commands, ``conf/`` defaults, the ``fast`` preset):

* ``given``: ``gcgs prepare`` with the scene's masks (what the DVC pipeline trains on);
* ``none``: ``gcgs prepare --masks none`` (``--no-masks`` before 2026-12-08, when prepare
  began to derive masks itself), then every stage on it;
* ``derived``: the ``none`` scene and its init, ``gcgs masks`` (its overlays side by side in
  ``reports/renders/masks/SCENE.png``), then ``init`` again and every stage on the new scene.

Every mode is scored against the ``given`` scene (the DTU protocol culls the mesh with the true
masks of the input views). Per (scene, mode, seed) it records the Chamfer (overall, accuracy,
completeness), the surfels and their budget,
the training wall and CPU time, and the mesh's pixels outside the held-out masks as a share
of their area (``extra_share``; ``missing_share`` the mask pixels the mesh misses), over every
view the training did not see (scan24: its 46 held-out masks; it has no Chamfer). Cells run
two at a time, one thread each.

    python experiments/masks_modes_2026-12-05/run.py --seeds 0 [--scenes synth_thin ...] [--work data/masks_modes]

Writes ``reports/experiments/masks_modes_2026-12-05/results.csv`` and ``results.md``, and per
scene and mode the held-out overlay of the first seed's mesh (``gcgs render-scene``'s:
its silhouette against held-out masks) as ``reports/renders/masks/SCENE_heldout_MODE.png``.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[2]
MODES = ("given", "derived", "none")
ENV = {**os.environ, "GCGS_THREADS": "1", "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


def gcgs(*args: str, log: Path) -> None:
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as f:
        f.write("$ gcgs " + " ".join(args) + "\n")
        f.flush()
        res = subprocess.run(["gcgs", *args], cwd=REPO, env=ENV, stdout=f, stderr=subprocess.STDOUT)
    if res.returncode != 0:
        raise RuntimeError(f"gcgs {' '.join(args)} failed ({res.returncode}); log {log}")


def scene_src(scene: str) -> str:
    """The scene's source folder, from params ``scenes`` (a synthetic scene or a real scan)."""
    return yaml.safe_load((REPO / "params.yaml").read_text())["scenes"][scene]["src"]


def prepare_mode(scene: str, mode: str, work: Path) -> None:
    """The prepared scene, its init and priors of one mode (once for every seed)."""
    d, log = work / scene / mode, work / scene / mode / "log.txt"
    if (d / "priors").is_dir():
        return
    src = REPO / scene_src(scene)
    if mode == "derived":
        prepare_mode(scene, "none", work)
        none = work / scene / "none"
        gcgs("masks", "--scene", str(none / "scene"), "--init-dir", str(none / "init"), "--out-scene", str(d / "scene"),
             "--overlays", str(d / "overlays"), log=log)
        overlay_strip(d / "overlays", REPO / "reports" / "renders" / "masks" / f"{scene}.png")
    else:
        gcgs("prepare", "--src", str(src), "--out", str(d / "scene"), "--name", scene,
             *(["--masks", "none"] if mode == "none" else []), log=log)
    gcgs("init", "--scene", str(d / "scene"), "--out-dir", str(d / "init"), "--metrics", str(d / "init.json"), log=log)
    gcgs("priors", "--scene", str(d / "scene"), "--init-dir", str(d / "init"), "--out-dir", str(d / "priors"), log=log)


def overlay_strip(overlays: Path, out: Path) -> None:
    """The views' overlays side by side at half size, each labelled with its view id."""
    import cv2

    tiles = []
    for png in sorted(overlays.glob("*.png")):
        im = cv2.imread(str(png))
        im = cv2.resize(im, (im.shape[1] // 2, im.shape[0] // 2), interpolation=cv2.INTER_AREA)
        cv2.putText(im, f"view {int(png.stem)}", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(im)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), np.concatenate(tiles, axis=1), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def run_cell(scene: str, mode: str, seed: int, work: Path) -> dict:
    d, c = work / scene / mode, work / scene / mode / f"seed{seed}"
    log = c / "log.txt"
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["optimize"]["seed"] = seed
    c.mkdir(parents=True, exist_ok=True)
    (c / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    p = ["--params", str(c / "params.yaml")]
    if not (c / "metrics.json").exists():
        gcgs("optimize", "--scene", str(d / "scene"), "--init-dir", str(d / "init"), "--priors-dir", str(d / "priors"),
             "--out-dir", str(c / "surfels"), "--checkpoint", str(c / "ckpt.pt"), "--metrics", str(c / "train.json"),
             "--live-dir", str(c / "curves"), "--no-progress", *p, log=log)
        gcgs("mesh", "--scene", str(d / "scene"), "--surfels-dir", str(c / "surfels"), "--init-dir", str(d / "init"),
             "--out-dir", str(c / "mesh"), *p, log=log)
        # Scored against the given scene in every mode: the same images and cameras, and the true
        # masks, which the DTU protocol culls the mesh with (a scene without masks has none).
        given = work / scene / "given" / "scene"
        given = given if given.is_dir() else REPO / "data" / "scenes" / scene  # the DVC pipeline's, when not run here
        gcgs("score", scene, "--scene", str(given), "--surfels-dir", str(c / "surfels"), "--mesh-dir",
             str(c / "mesh"), "--train-timing", str(c / "train.json"), "--out", str(c / "metrics.json"), *p, log=log)
    m = json.loads((c / "metrics.json").read_text())
    t = json.loads((c / "train.json").read_text())
    extra, missing, mesh_iou = heldout_silhouette(scene, d / "scene", c / "mesh" / "mesh.ply")
    chamfer = m.get("chamfer") or {}  # a real scan has no ground truth: held-out views only
    return {"scene": scene, "masks": mode, "seed": seed, "overall_mm": chamfer.get("overall_mm", np.nan),
            "accuracy_mm": chamfer.get("accuracy_mm", np.nan), "completeness_mm": chamfer.get("completeness_mm", np.nan),
            "heldout_mesh_iou": mesh_iou,
            "surfels": t["surfels_final"], "surfel_budget": t.get("surfel_budget"), "train_wall_s": t["wall_s"], "train_cpu_s": t["cpu_s"],
            "peak_rss_mb": t["peak_rss_mb"], "extra_share": extra, "missing_share": missing}


def heldout_silhouette(scene: str, scene_dir: Path, mesh_ply: Path) -> tuple[float, float, float]:
    """The mesh's silhouette against the true masks of every view the training did not see,
    at 400 px wide: (pixels outside the masks, mask pixels missed), each summed over the
    views and divided by the masks' total area, and the mean IoU over the views."""
    sys.path.insert(0, str(REPO / "src"))
    from pipeline.data import dtu
    from pipeline.data.heldout import load_heldout
    from pipeline.evaluation.gt import read_mesh
    from pipeline.raycast import MeshCaster

    from pipeline.evaluation.heldout import iou

    heldout = load_heldout(REPO / scene_src(scene), dtu.image_ids(scene_dir), 400)
    caster = MeshCaster(*read_mesh(mesh_ply))
    extra = missing = area = 0
    ious = []
    for m in range(len(heldout.view_ids)):
        hit = caster.cast(heldout.K[m], heldout.world_to_cam[m], heldout.height, heldout.width).depth_mm > 0
        gt = heldout.masks[m]
        extra += int((hit & ~gt).sum())
        missing += int((~hit & gt).sum())
        area += int(gt.sum())
        ious.append(iou(hit, gt))
    return extra / area, missing / area, float(np.mean(ious))


def heldout_pictures(scenes: list[str], modes: list[str], seed: int, work: Path) -> None:
    """The held-out overlay (mesh silhouette vs held-out masks) of each (scene, mode)'s
    ``seed`` run, to ``reports/renders/masks/SCENE_heldout_MODE.png``."""
    sys.path.insert(0, str(REPO / "src"))
    from pipeline.reports.renders import heldout_overlay, write_png

    for scene in scenes:
        for mode in modes:
            d = work / scene / mode
            shot = heldout_overlay(d / "scene", REPO / scene_src(scene), d / f"seed{seed}" / "mesh" / "mesh.ply")
            write_png(REPO / "reports" / "renders" / "masks" / f"{scene}_heldout_{mode}.png", shot.rgb)


def markdown(rows: list[dict], commit: str) -> str:
    lines = ["# Masks given / derived / none (synthetic scenes, `fast`)", "",
             f"Commit {commit}; `experiments/masks_modes_2026-12-05/run.py`; cells two at a time, one thread each. "
             "Chamfer in mm (mean ± half-range over seeds); surfels and training CPU as the mean; "
             "extra / missing: the mesh's pixels outside / the mask pixels it misses, over every held-out "
             "view, as a share of the masks' area.", "",
             "| scene | masks | seeds | overall | accuracy | completeness | held-out mesh IoU | surfels | budget | train CPU s | extra | missing |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for mode in MODES:
            rs = [r for r in rows if r["scene"] == scene and r["masks"] == mode]
            if not rs:
                continue

            def pm(k, rs=rs):
                v = np.array([r[k] for r in rs], float)
                if np.isnan(v).all():
                    return "-"
                return f"{v.mean():.3f}" + (f" ± {(v.max() - v.min()) / 2:.3f}" if len(v) > 1 else "")

            mean = lambda k, rs=rs: float(np.mean([r[k] for r in rs]))  # noqa: E731
            lines.append(f"| {scene} | {mode} | {len(rs)} | {pm('overall_mm')} | {pm('accuracy_mm')} | "
                         f"{pm('completeness_mm')} | {pm('heldout_mesh_iou')} | {mean('surfels'):.0f} | {mean('surfel_budget'):.0f} | {mean('train_cpu_s'):.0f} | "
                         f"{100 * mean('extra_share'):.1f}% | {100 * mean('missing_share'):.1f}% |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["synth_thin", "synth_relief", "synth_textureless", "scan24"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--work", default="data/masks_modes")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", default="reports/experiments/masks_modes_2026-12-05/results")
    args = ap.parse_args()
    work = (REPO / args.work).resolve()
    t0 = time.time()
    with ThreadPoolExecutor(args.jobs) as pool:  # the per-mode set-up first ('derived' needs 'none')
        list(pool.map(lambda sm: prepare_mode(*sm, work), [(s, m) for s in args.scenes for m in args.modes if m != "derived"]))
        list(pool.map(lambda sm: prepare_mode(*sm, work), [(s, "derived") for s in args.scenes if "derived" in args.modes]))
        cells = [(s, m, seed) for s in args.scenes for m in args.modes for seed in args.seeds]
        rows = list(pool.map(lambda c: run_cell(*c, work), cells))
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    out = REPO / args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) + ["commit"])
        w.writeheader()
        w.writerows({**r, "commit": commit} for r in rows)
    out.with_suffix(".md").write_text(markdown(rows, commit))
    heldout_pictures(args.scenes, args.modes, min(args.seeds), work)
    print(out.with_suffix(".md").read_text(), f"\n{time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
