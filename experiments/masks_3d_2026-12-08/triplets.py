"""scan24 with its masks withheld on several view triplets (issue 77's "Done when"): each
triplet prepared from the full 49-view scan three ways and run through the `gcgs` stages
(the `fast` preset, one seed): masks ``given`` (``--masks capture``), ``derived``
(``--masks derive``: the 3D labelling of pipeline.labelling, no second pass) and ``none``.
Per run: the held-out mesh IoU over every view the triplet does not train on (``gcgs
score``), and for ``derived`` each input view's mask IoU against the true mask.

    python experiments/masks_3d_2026-12-08/triplets.py --src ../shared/data/dtu/scan24 \
        [--triplets 23,24,33 15,16,26 30,31,40] [--work data/masks_3d] [--jobs 2]

Writes ``reports/experiments/masks_3d_2026-12-08/triplets.csv`` and ``.md``.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[2]
OUT = REPO / "reports" / "experiments" / "masks_3d_2026-12-08"
ENV = {**os.environ, "GCGS_THREADS": "1", "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
MODES = {"given": "capture", "derived": "derive", "none": "none"}


def gcgs(*args, log: Path) -> None:
    with open(log, "a") as f:
        f.write("$ gcgs " + " ".join(map(str, args)) + "\n")
        f.flush()
        res = subprocess.run(["gcgs", *map(str, args)], cwd=REPO, env=ENV, stdout=f, stderr=subprocess.STDOUT)
    if res.returncode != 0:
        raise RuntimeError(f"gcgs {args[0]} failed ({res.returncode}); log {log}")


def run(src: Path, views: list[int], mode: str, work: Path) -> dict:
    name = f"t{'_'.join(map(str, views))}_{mode}"
    d = work / name
    d.mkdir(parents=True, exist_ok=True)
    log = d / "log.txt"
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["scenes"] = {name: {"src": str(src), "gt": None, "masks": MODES[mode]}}
    (d / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    p = ["--params", d / "params.yaml"]
    if not (d / "metrics.json").is_file():
        gcgs("prepare", "--src", src, "--out", d / "scene", "--name", name, "--views", *views, "--masks", MODES[mode],
             *p, log=log)
        gcgs("init", "--scene", d / "scene", "--out-dir", d / "init", *p, log=log)
        gcgs("priors", "--scene", d / "scene", "--init-dir", d / "init", "--out-dir", d / "priors", *p, log=log)
        gcgs("optimize", "--scene", d / "scene", "--init-dir", d / "init", "--priors-dir", d / "priors", "--out-dir",
             d / "surfels", "--metrics", d / "train.json", "--no-progress", *p, log=log)
        gcgs("mesh", "--scene", d / "scene", "--surfels-dir", d / "surfels", "--init-dir", d / "init", "--out-dir",
             d / "mesh", *p, log=log)
        gcgs("score", name, "--scene", d / "scene", "--surfels-dir", d / "surfels", "--mesh-dir", d / "mesh",
             "--train-timing", d / "train.json", "--out", d / "metrics.json", *p, log=log)
    held = json.loads((d / "metrics.json").read_text())["heldout"]
    row = {"triplet": " ".join(map(str, views)), "mode": mode, "heldout_mesh_iou": held.get("mesh_iou_mean"),
           "heldout_views": held.get("views")}
    if mode == "derived":
        from pipeline.data import dtu

        derived = dtu.load_scene(d / "scene", view_ids=None)
        true = dtu.load_masks(src, size=(derived.width, derived.height))
        ious = [float(((m > 0.5) & true[v]).sum() / ((m > 0.5) | true[v]).sum()) for v, m in
                zip(derived.view_ids, derived.masks)]
        meta = json.loads((d / "scene" / "scene.json").read_text())["derived_masks"]
        row["mask_iou_per_view"] = " ".join(f"{x:.3f}" for x in ious)
        row["methods"] = " ".join(v["method"] for v in meta["views"].values())
    return row


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--src", required=True)
    ap.add_argument("--triplets", nargs="+", default=["23,24,33", "15,16,26", "30,31,40"])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    ap.add_argument("--work", default="data/masks_3d")
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    src, work = Path(args.src).resolve(), (REPO / args.work)
    cells = [([int(v) for v in t.split(",")], m) for t in args.triplets for m in args.modes]
    with ThreadPoolExecutor(args.jobs) as pool:
        rows = list(pool.map(lambda c: run(src, c[0], c[1], work), cells))
    OUT.mkdir(parents=True, exist_ok=True)
    keys = ["triplet", "mode", "heldout_mesh_iou", "heldout_views", "mask_iou_per_view", "methods"]
    with open(OUT / "triplets.csv", "w", newline="") as f:
        w = csv.DictWriter(f, keys)
        w.writeheader()
        w.writerows(rows)
    lines = ["| triplet | " + " | ".join(args.modes) + " | derived masks' IoU per view |",
             "| --- " * (len(args.modes) + 2) + "|"]
    for t in args.triplets:
        r = {x["mode"]: x for x in rows if x["triplet"] == t.replace(",", " ")}
        cells = " | ".join(f"{r[m]['heldout_mesh_iou']:.3f}" for m in args.modes)
        masks = f"{r['derived']['mask_iou_per_view']} ({r['derived']['methods']})" if "derived" in r else ""
        lines.append(f"| {t.replace(',', ' ')} | {cells} | {masks} |")
    (OUT / "triplets.md").write_text("Held-out mesh IoU (scan24, fast, seed 0)\n\n" + "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
