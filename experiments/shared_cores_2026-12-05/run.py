"""One `fast` training alone against two at once on the same machine, with the thread pools
as `gcgs` sizes them (every process takes the cores its affinity and cgroup allow) and with
`GCGS_THREADS=1` each (what docs/pipeline.md tells a sweep to do).

    python experiments/shared_cores_2026-12-05/run.py [--scene synth_relief]

Needs the DVC outputs of the scene (data/scenes, data/init, data/priors). Writes
reports/experiments/shared_cores_2026-12-05/results.md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def launch(scene: str, out: Path, threads: str | None) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k not in ("GCGS_THREADS", "NUMBA_NUM_THREADS", "OMP_NUM_THREADS")}
    if threads:
        env["GCGS_THREADS"] = threads
    cmd = ["gcgs", "optimize", "--scene", f"data/scenes/{scene}", "--init-dir", f"data/init/{scene}",
           "--priors-dir", f"data/priors/{scene}", "--out-dir", str(out / "surfels"), "--checkpoint", str(out / "c.pt"),
           "--metrics", str(out / "train.json"), "--live-dir", str(out / "curves"), "--no-progress"]
    return subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def run(scene: str, jobs: int, threads: str | None, root: Path) -> list[dict]:
    outs = [Path(tempfile.mkdtemp(dir=root)) for _ in range(jobs)]
    t0 = time.perf_counter()
    procs = [launch(scene, o, threads) for o in outs]
    for p in procs:
        _, err = p.communicate()
        if p.returncode != 0:
            raise RuntimeError(err)
    wall = time.perf_counter() - t0
    return [{**json.loads((o / "train.json").read_text()), "batch_wall_s": wall} for o in outs]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="synth_relief")
    ap.add_argument("--out", default="reports/experiments/shared_cores_2026-12-05/results.md")
    args = ap.parse_args()
    sys.path.insert(0, str(REPO / "src"))
    from pipeline.threads import available_cores

    cores, why = available_cores({k: v for k, v in os.environ.items() if k != "GCGS_THREADS"})
    rows = []
    with tempfile.TemporaryDirectory() as root:
        for label, jobs, threads in (("one alone", 1, None), ("two at once", 2, None),
                                     ("two at once, GCGS_THREADS=1", 2, "1"), ("one alone, GCGS_THREADS=1", 1, "1")):
            res = run(args.scene, jobs, threads, Path(root))
            rows.append((label, res))
            print(label, [round(r["wall_s"], 1) for r in res], flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True).stdout.strip()
    lines = [f"# Shared cores: `fast` on {args.scene}, one training alone against two at once", "",
             f"Commit {commit}; `experiments/shared_cores_2026-12-05/run.py`; {cores} cores available ({why}); "
             f"backend {rows[0][1][0]['backend']}. Wall and CPU seconds of each training (`train.json`); "
             "the batch's wall time is from the first start to the last end.", "",
             "| run | trainings | threads each | wall s each | CPU s each | batch wall s | trainings per hour |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for label, res in rows:
        n = len(res)
        threads = "1" if "GCGS_THREADS=1" in label else str(cores)
        walls = " / ".join(f"{r['wall_s']:.1f}" for r in res)
        cpus = " / ".join(f"{r['cpu_s']:.1f}" for r in res)
        batch = res[0]["batch_wall_s"]
        lines.append(f"| {label} | {n} | {threads} | {walls} | {cpus} | {batch:.1f} | {3600 * n / batch:.0f} |")
    out = REPO / args.out
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(out.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
