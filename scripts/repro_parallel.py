"""`dvc repro` on several single-threaded workers: every stage that `dvc status` calls
changed, and everything downstream of it whose dependencies then differ from what dvc.lock
records, run in dependency order, then recorded in dvc.lock with `dvc commit`'s work
(README, first section). As with `dvc repro`, a stage that writes the same bytes again (the
priors stage when a Table II row is added) leaves the stages after it alone.

On the 2-core machines here one training barely gains from a second numba thread: two fast
trainings with their scoring, one thread each and at once, took 146 s against 2 x 125 s one
after the other (2026-11-28). Each stage runs exactly its `cmd` from dvc.yaml, after its
outputs are removed as `dvc repro` removes them; a failed stage stops its dependents only,
and its log is kept. A file STOP in the log folder
ends a run cleanly: no new stage starts, the running ones finish and are committed, and a
later run takes up what is left.

    python scripts/repro_parallel.py [--jobs 2] [--logs .dvc/tmp/repro_parallel] [--dry] [--done STAGE ...]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path


def schedule_order(deps: dict[str, set[str]], weight: dict[str, float]) -> list[str]:
    """A valid run order of the stages in ``deps`` (stage -> the stages it needs, restricted
    to those that run): among the ready stages, the one heading the heaviest chain first."""
    dependents: dict[str, set[str]] = {s: set() for s in deps}
    for s, ds in deps.items():
        for d in ds:
            dependents[d].add(s)
    chain: dict[str, float] = {}

    def heaviest(s: str) -> float:
        if s not in chain:
            chain[s] = weight.get(s, 1.0) + max((heaviest(t) for t in dependents[s]), default=0.0)
        return chain[s]

    done: set[str] = set()
    order: list[str] = []
    while len(order) < len(deps):
        ready = [s for s in deps if s not in done and deps[s] <= done]
        if not ready:
            raise ValueError(f"dependency cycle among {sorted(set(deps) - done)}")
        s = max(ready, key=lambda r: (heaviest(r), r))
        order.append(s)
        done.add(s)
    return order


def _weight(name: str) -> float:
    """Rough cost (minutes on one thread) for the ordering only."""
    if "scan24" in name and name.startswith(("optimize", "renders")):
        return 6.0
    if name.startswith(("optimize", "variant-train")):
        return 1.5
    return 0.5


def _remove_outs(stage) -> None:
    """What `dvc repro` does before a stage runs (without the repo lock, which a background
    `dvc commit` may hold): its outputs go, unless declared persistent."""
    for out in stage.outs:
        if out.persist:
            continue
        path = Path(out.fs_path)
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def deps_changed(stage) -> bool:
    """Whether a file or folder ``stage`` depends on differs from what dvc.lock records for it:
    what `dvc repro` checks before running a stage downstream of one that ran. Hashing goes
    through DVC's state database, without the repo lock a background commit may hold."""
    from dvc.dependency.param import ParamsDependency

    return any(dep.status() for dep in stage.deps if not isinstance(dep, ParamsDependency))


def commit_stages(names: list[str]) -> None:
    """`dvc commit -f` of the stages ``names`` with one read and one write of dvc.lock: the
    CLI reads the 1.3 MB lock once per target and again to write it (~25 s a stage here)."""
    from dvc.repo import Repo

    repo = Repo(".")
    with repo.lock:
        by_name = {s.addressing: s for s in repo.index.stages}
        stages = [by_name[n] for n in names]
        for stage in stages:
            stage.save()
            stage.commit()
        for path in {s.dvcfile.path for s in stages}:
            group = [s for s in stages if s.dvcfile.path == path]
            group[0].dvcfile.dump_stages(group, update_pipeline=False)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--logs", default=".dvc/tmp/repro_parallel")
    ap.add_argument("--dry", action="store_true", help="print the stages and their order, run nothing")
    ap.add_argument("--done", nargs="*", default=[], metavar="STAGE",
                    help="stages an interrupted run finished but did not commit: committed, not rerun")
    ap.add_argument("--commit-only", nargs="+", metavar="STAGE", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.commit_only:
        commit_stages(args.commit_only)
        return

    import networkx as nx
    from dvc.repo import Repo

    repo = Repo(".")
    graph = repo.index.graph  # edge: stage -> a stage it depends on
    stages = {s.addressing: s for s in graph.nodes if s.cmd}
    with repo.lock:
        stale = {name for name, s in stages.items() if s.changed()}
    run = set(stale)
    for name in stale:
        run |= {a.addressing for a in nx.ancestors(graph, stages[name]) if a.cmd}
    deps = {n: {d.addressing for d in graph.successors(stages[n]) if d.addressing in run} for n in run}
    order = schedule_order(deps, {n: _weight(n) for n in run})
    print(f"{len(order)} stages to run ({len(stale)} changed; the others only if a dependency comes out changed), "
          f"{args.jobs} workers", flush=True)
    if args.dry:
        print("\n".join(order))
        return

    logs = Path(args.logs)
    logs.mkdir(parents=True, exist_ok=True)
    (logs / "STOP").unlink(missing_ok=True)  # an earlier run's
    env = {**os.environ, "NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    running: dict[str, tuple[subprocess.Popen, float]] = {}
    done: set[str] = set()
    failed: set[str] = set()
    to_commit: list[str] = []
    committing: tuple[subprocess.Popen, list[str]] | None = None
    unknown = set(args.done) - set(order)
    if unknown:
        raise SystemExit(f"--done names stages that are not to run: {sorted(unknown)}")
    pending = [n for n in order if n not in args.done]
    done.update(args.done)
    to_commit.extend(args.done)

    def start_commit(names: list[str]) -> tuple[subprocess.Popen, list[str]]:
        # In the background: committing hashes and caches the outputs, and the workers must not
        # wait for it (it takes the repo lock; the stages' commands don't).
        return subprocess.Popen([sys.executable, __file__, "--commit-only", *names]), names

    while pending or running or to_commit or committing:
        blocked = {n for n in pending if deps[n] & failed}
        for n in blocked:
            pending.remove(n)
            failed.add(n)
            print(f"SKIP {n}: a stage it needs failed", flush=True)
        if committing is None or committing[0].poll() is not None:
            if committing is not None:
                if committing[0].returncode != 0:
                    raise SystemExit(f"dvc commit failed for {committing[1]}")
                print(f"{time.strftime('%H:%M:%S')} committed {len(committing[1])} stage(s)", flush=True)
                committing = None
            if to_commit and (len(to_commit) >= 12 or not (pending or running)):
                committing, to_commit = start_commit(to_commit), []
        if pending and (logs / "STOP").exists():
            print(f"{time.strftime('%H:%M:%S')} STOP: {len(pending)} stage(s) left to a later run", flush=True)
            pending = []
        for n in list(pending):
            if len(running) >= args.jobs:
                break
            if deps[n] <= done:
                pending.remove(n)
                if n not in stale and not deps_changed(stages[n]):
                    done.add(n)  # its dvc.lock entry stands
                    print(f"{time.strftime('%H:%M:%S')} unchanged {n}: its dependencies came out as recorded",
                          flush=True)
                    continue
                _remove_outs(stages[n])
                log = open(logs / f"{n.replace('/', '_')}.log", "w")
                running[n] = (subprocess.Popen(stages[n].cmd, shell=True, cwd=repo.root_dir, env=env, stdout=log,
                                               stderr=subprocess.STDOUT), time.time())
                print(f"{time.strftime('%H:%M:%S')} start {n}", flush=True)
        time.sleep(2)
        for n, (proc, t0) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[n]
            ok = proc.returncode == 0
            (done if ok else failed).add(n)
            if ok:
                to_commit.append(n)
            print(f"{time.strftime('%H:%M:%S')} {'done' if ok else 'FAILED'} {n} ({time.time() - t0:.0f} s)", flush=True)
    print(f"finished: {len(done)} done, {len(failed)} failed or skipped", flush=True)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
