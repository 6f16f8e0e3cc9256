"""Train every preset of the ladder on the synthetic suite with several seeds, mesh and score
each run, and write ``reports/presets.{csv,md,png}`` (docs/presets.md).

Each run is ``gcgs optimize``, ``gcgs mesh`` and ``gcgs score`` with the preset's params
(``conf/optimize/PRESET.yaml`` composed as ``gcgs params optimize=PRESET`` would, the seed
set) on the DVC outputs of the scene (``--inputs``: scenes/, init/, priors/, and the ground
truth that params name, resolved against the same checkout). Runs whose metrics exist at this
commit are kept (the ladder resumes); the report is rewritten after each run. ``--jobs`` runs
at once, each on ``--threads`` threads (GCGS_THREADS), cheapest preset first, so that the
ladder's lower steps land first. Every row records the commit it ran on; the code must be
committed (a dirty ``src/`` or ``conf/`` is refused).

    python scripts/presets.py [--presets quick fast ...] [--seeds 0 1 2] [--jobs 2] [--inputs data]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import yaml

from pipeline.config.params import compose_params
from pipeline.reports.presets import LADDER, read_rows, write_report

REPO = Path(__file__).resolve().parents[1]
SCENES = ("synth_textureless", "synth_relief", "synth_thin")


def commit_of_code() -> str:
    dirty = subprocess.run(["git", "status", "--porcelain", "--", "src", "conf", "scripts"], cwd=REPO,
                           capture_output=True, text=True, check=True).stdout.strip()
    if dirty:
        sys.exit(f"scripts/presets.py: uncommitted changes under src/, conf/ or scripts/; commit them first:\n{dirty}")
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                          check=True).stdout.strip()


def release(reports: list[Path]) -> None:
    """The committed reports are this runner's own (a fresh clone's copies carry no gcgs
    mark, so the writer would refuse them): their rows are read before this, and rewritten."""
    for path in reports:
        path.unlink(missing_ok=True)


def gcgs(args: list[str], log: Path, env: dict) -> None:
    with open(log, "a") as f:
        f.write("$ gcgs " + " ".join(args) + "\n")
        f.flush()
        res = subprocess.run([sys.executable, "-m", "pipeline.cli", *args], cwd=REPO, env=env, stdout=f,
                             stderr=subprocess.STDOUT)
    if res.returncode != 0:
        raise RuntimeError(f"gcgs {' '.join(args)} failed ({res.returncode}); log {log}")


def with_inputs(params: dict, inputs: Path) -> dict:
    """``params`` with the scenes' relative ``src`` and ``gt`` paths (``data/...``, relative to
    a checkout) resolved against the checkout that holds ``inputs`` (its ``data/`` folder), so
    that a ladder run from another folder scores against the same ground truth."""
    root = inputs.parent
    scenes = {name: {k: (str(root / v) if k in ("src", "gt") and v and not Path(v).is_absolute() else v)
                     for k, v in entry.items()}
              for name, entry in params.get("scenes", {}).items()}
    return {**params, "scenes": scenes}


def run_one(preset: str, scene: str, seed: int, params: dict, inputs: Path, work: Path, threads: int,
            commit: str) -> dict:
    cell = work / preset / scene / f"seed{seed}"
    row_file = cell / "row.json"
    if row_file.is_file():
        row = json.loads(row_file.read_text())
        if row["commit"] == commit:
            return row
        shutil.rmtree(cell)  # a run of other code must not land in this commit's ladder
    cell.mkdir(parents=True, exist_ok=True)
    params = {**with_inputs(params, inputs), "optimize": {**params["optimize"], "seed": seed}}
    (cell / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    env = dict(os.environ, GCGS_THREADS=str(threads))
    log, p = cell / "log.txt", ["--params", str(cell / "params.yaml")]
    src = [f"--scene={inputs}/scenes/{scene}", f"--init-dir={inputs}/init/{scene}"]
    gcgs(["optimize", *src, f"--priors-dir={inputs}/priors/{scene}", f"--out-dir={cell}/surfels",
          f"--checkpoint={cell}/ckpt.pt", f"--metrics={cell}/train.json", f"--live-dir={cell}/curves", "--no-progress", *p],
         log, env)
    gcgs(["mesh", *src, f"--surfels-dir={cell}/surfels", f"--out-dir={cell}/mesh", *p], log, env)
    gcgs(["score", scene, f"--scene={inputs}/scenes/{scene}", f"--surfels-dir={cell}/surfels",
          f"--mesh-dir={cell}/mesh", f"--train-timing={cell}/train.json", f"--out={cell}/metrics.json", *p], log, env)
    m = json.loads((cell / "metrics.json").read_text())
    t = json.loads((cell / "train.json").read_text())
    ch = m["chamfer"]
    row = {"preset": preset, "scene": scene, "seed": seed, "overall_mm": ch["overall_mm"],
           "accuracy_mm": ch["accuracy_mm"], "completeness_mm": ch["completeness_mm"], "train_wall_s": t["wall_s"],
           "train_cpu_s": t["cpu_s"], "peak_rss_mb": t["peak_rss_mb"], "commit": commit}
    row_file.write_text(json.dumps(row))
    return row


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--presets", nargs="+", default=list(LADDER))
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--inputs", type=Path, default=REPO / "data",
                    help="a checkout's data/ folder: scenes/, init/, priors/ and the synthetic scenes' ground truth")
    ap.add_argument("--work", type=Path, default=REPO / "data" / "presets")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1, help="GCGS_THREADS of each run")
    ap.add_argument("--report-only", action="store_true", help="rewrite reports/presets.* from reports/presets.csv")
    args = ap.parse_args()
    out = REPO / "reports"
    reports = [out / "presets.csv", out / "presets.md", out / "presets.png"]
    if args.report_only:
        rows = read_rows(reports[0])
        release(reports)
        write_report(rows, *reports)
        return 0
    commit = commit_of_code()
    order = {p: i for i, p in enumerate(LADDER)}
    runs = sorted(((p, s, seed) for p in args.presets for s in args.scenes for seed in args.seeds),
                  key=lambda c: (order.get(c[0], len(order)), c[2], c[1]))
    rows: list[dict] = []
    old = out / "presets.csv"
    if old.is_file():  # rows of other presets or seeds at the same commit stay
        rows = [r for r in read_rows(old) if r["commit"] == commit]
    release(reports)
    lock = threading.Lock()
    params = {p: compose_params([f"optimize={p}"]) for p in args.presets}  # Hydra's compose is not thread-safe

    def one(run: tuple[str, str, int]) -> None:
        row = run_one(*run, params[run[0]], args.inputs.resolve(), args.work.resolve(), args.threads, commit)
        with lock:
            rows[:] = [r for r in rows if (r["preset"], r["scene"], r["seed"]) != run] + [row]
            write_report(rows, *reports)
            print(f"[presets] {run}: {row['overall_mm']:.3f} mm, {row['train_cpu_s']:.0f} s CPU", flush=True)

    failed = []
    with ThreadPoolExecutor(args.jobs) as pool:
        for run, f in [(r, pool.submit(one, r)) for r in runs]:
            try:
                f.result()
            except RuntimeError as exc:  # one failed run does not stop the others
                failed.append(run)
                print(f"[presets] {run}: {exc}", file=sys.stderr, flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
