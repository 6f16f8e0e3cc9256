"""``python -m pipeline.sweep``: a Hydra app whose job is one (scene, variant) cell, so that
Hydra's launchers run a sweep in parallel on this machine (``hydra/launcher=local``, joblib)
or on a SLURM cluster (``hydra/launcher=slurm``, submitit); see docs/sweeps.md.

A cell is the pipeline config composed from ``conf/`` with the sweep's overrides (a variant)
and one scene (``cell.scene``). Its job reproduces ``cell.stage@SCENE`` of dvc.yaml with that
config, in a git worktree of the committed code (``cells/NAME`` under the job's output
folder) whose DVC cache is the repository's: a stage already computed with the same code,
data and params, by any earlier cell or ``dvc repro``, is restored from DVC's run cache
instead of rerun, so changing one variant's setting reruns only that variant's cells. The
job copies the cell's ``reports/metrics/SCENE.json`` next to Hydra's record of the cell and
removes the worktree.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from pipeline.config.params import CONF_DIR, dump_params
from pipeline.errors import ConfigError, InputError
from pipeline.evaluation.record import SceneMetrics

SWEEP_CONFIG = "sweep"
# Files whose uncommitted changes a cell would silently not run (it checks out HEAD).
CODE_PATHS = ("src", "dvc.yaml", "data/raw", "data/published", "models")


def cell_params(config: dict, scene: str) -> dict:
    """params.yaml of a cell: the composed config without the sweep's own keys, with
    ``scenes`` reduced to ``scene``."""
    params = {k: v for k, v in config.items() if k not in ("cell", "hydra")}
    scenes = params.get("scenes") or {}
    if scene not in scenes:
        raise ConfigError(f"cell.scene={scene!r} is not in `scenes` ({sorted(scenes)})")
    params["scenes"] = {scene: scenes[scene]}
    return params


def _run(cmd: list[str], cwd: Path, env: dict | None = None) -> str:
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env)
    if res.returncode != 0:
        raise RuntimeError(f"`{' '.join(cmd)}` in {cwd} failed ({res.returncode}):\n{res.stdout}\n{res.stderr}")
    return res.stdout


def check_committed(repo: Path) -> None:
    """Refuse to run cells of code that differs from HEAD (the worktree checks out HEAD)."""
    dirty = _run(["git", "status", "--porcelain", "--", *CODE_PATHS], repo).strip()
    if dirty:
        raise InputError(f"{repo}: uncommitted changes in {', '.join(CODE_PATHS)}; a sweep runs the committed "
                         f"code, commit them first:\n{dirty}")


def run_cell(params: dict, scene: str, stage: str, out_dir: Path, repo: Path) -> dict:
    """Reproduce ``stage@scene`` with ``params`` in a worktree under ``out_dir``; return and
    keep (``out_dir/metrics.json``) the scene's metrics ({} for a stage upstream of them)."""
    dvc = str(Path(sys.executable).with_name("dvc"))
    cache = _run([dvc, "cache", "dir"], repo).strip()
    out_dir.mkdir(parents=True, exist_ok=True)
    cell = out_dir / "worktree"
    if cell.exists():  # left by an interrupted job
        _run(["git", "worktree", "remove", "--force", str(cell)], repo)
    _run(["git", "worktree", "add", "--detach", str(cell), "HEAD"], repo)
    try:
        _run([dvc, "cache", "dir", "--local", cache], cell)
        (cell / "params.yaml").write_text(dump_params(params))
        (out_dir / "params.yaml").write_text(dump_params(params))
        # The committed metrics are not this cell's: only the score stage may write them back.
        metrics = cell / "reports" / "metrics" / f"{scene}.json"
        metrics.unlink(missing_ok=True)
        # The stages' `gcgs` must import the worktree's code, not an installed or PYTHONPATH copy.
        env = os.environ | {"PYTHONPATH": str(cell / "src")}
        log = _run([dvc, "repro", f"{stage}@{scene}"], cell, env)
        (out_dir / "dvc_repro.log").write_text(log)
        if not metrics.is_file():  # a stage upstream of score
            return {}
        shutil.copy(metrics, out_dir / "metrics.json")
        return SceneMetrics.read(metrics).to_json()
    finally:
        _run(["git", "worktree", "remove", "--force", str(cell)], repo)


@hydra.main(config_path=str(CONF_DIR), config_name=SWEEP_CONFIG, version_base="1.3")
def main(cfg: DictConfig) -> dict:
    repo = Path(_run(["git", "rev-parse", "--show-toplevel"], Path.cwd()).strip())
    check_committed(repo)
    config = OmegaConf.to_container(cfg, resolve=True)
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    metrics = run_cell(cell_params(config, cfg.cell.scene), cfg.cell.scene, cfg.cell.stage, out_dir, repo)
    summary = {k: v for k, v in (metrics.get("chamfer") or metrics.get("heldout") or {}).items() if k != "per_view"}
    print(f"[sweep] {cfg.cell.scene} {list(HydraConfig.get().overrides.task)}: {summary} -> {out_dir}")
    return metrics


if __name__ == "__main__":
    main()
