"""One optimize run from files to files: load the scene, the init cloud and the priors,
train, write ``surfels.ply`` and ``train.json``, log the curves (DVCLive's layout)."""
from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

from pipeline import atomic
from pipeline.curves import CurveLog, check_curves_dir
from pipeline.config.loss import LossConfig
from pipeline.config.optimize import OptimizeConfig
from pipeline.data.dtu import load_scene
from pipeline.data.scene import Scene, check_made_from
from pipeline.errors import DegenerateResultError, OutputError
from pipeline.init.io import read_ply
from pipeline.optimize import MIN_SURFELS, init_from_cloud, make_views, uses_masks
from pipeline.optimize.region import region_from_views, surfel_budget
from pipeline.optimize.train import CHECKPOINT_KIND, TrainResult, train
from pipeline.optimize.views import TrainViews
from pipeline.surfels import SurfelParams, write_splats_3dgs_ply, write_surfel_ply

LOGGED_TERMS = ("total", "l1", "photo", "gcf", "mv", "mvgeo", "nor", "mvs", "dn", "dist", "mask", "surfels", "seconds")


def init_cloud_path(init_dir: str | Path) -> Path:
    """The init stage's cloud (``points.ply``, normalised frame) in ``init_dir``."""
    return Path(init_dir) / "points.ply"


def load_training_inputs(scene_dir: str | Path, init_dir: str | Path, priors_dir: str | Path | None,
                         cfg: OptimizeConfig, loss: LossConfig) -> tuple[Scene, SurfelParams, TrainViews]:
    """What a training starts from: the scene, the surfels made from the init's
    ``points.ply`` (normalised frame) and the training views with their priors and the
    init's depth maps; the init and the priors checked to be made from this scene."""
    scene = load_scene(scene_dir, view_ids=None)
    check_made_from(scene, init_dir, "init.json", "init")
    if priors_dir is not None and (loss.lambda_nor > 0 or loss.lambda_gcf > 0):
        check_made_from(scene, priors_dir, "priors.json", "priors")
    cloud_path = init_cloud_path(init_dir)
    depth_dir = Path(init_dir) / "depth"
    views = make_views(scene, priors_dir, cfg, loss, depth_dir if depth_dir.is_dir() else None)
    masks = views.training_masks()
    surfels = init_from_cloud(read_ply(cloud_path), scene, cfg, where=str(cloud_path),
                              region=region_from_views(scene, masks, cfg),
                              max_surfels=surfel_budget(scene, masks, cfg).surfels)
    return scene, surfels, views


def run_optimize(scene_dir: str | Path, init_dir: str | Path, priors_dir: str | Path, out_dir: str | Path,
                 cfg: OptimizeConfig, loss: LossConfig, checkpoint: str | Path, live_dir: str | Path | None = None,
                 progress: bool = True) -> TrainResult:
    """Train surfels for one scene and write ``out_dir/surfels.ply`` (2DGS layout, world mm),
    ``out_dir/splats_3dgs.ply`` (the same surfels for 3DGS viewers) and ``out_dir/train.json``
    (what was trained; no timings, so two runs give the same bytes). ``checkpoint`` (outside ``out_dir``) is resumed from when it matches and deleted
    once the output is written (only if it is a gcgs checkpoint); ``live_dir`` receives the
    curves (:mod:`pipeline.curves`; a resumed run keeps the rows before its checkpoint)."""
    out_dir, ckpt = Path(out_dir), Path(checkpoint)
    inputs = (scene_dir, init_dir, priors_dir)
    check_side_paths(out_dir, inputs, checkpoint=ckpt, live_dir=live_dir)
    with atomic.atomic_dir(out_dir, "surfels", inputs=inputs) as tmp:
        scene, surfels, views = load_training_inputs(scene_dir, init_dir, priors_dir, cfg, loss)
        live = CurveLog(live_dir, "train", LOGGED_TERMS, inputs) if live_dir is not None else None

        def on_log(row: dict) -> None:
            live.log(row["iteration"], row)

        ckpt.parent.mkdir(parents=True, exist_ok=True)
        result = train(surfels, views, cfg, loss, checkpoint=ckpt, on_log=on_log if live else None, progress=progress)
        if live is not None:
            live.end()
        if result.params.num < MIN_SURFELS:
            raise DegenerateResultError(
                f"{out_dir}: training ended with {result.params.num} surfels (fewer than {MIN_SURFELS}) from "
                f"{init_cloud_path(init_dir)}; nothing written (too few init points, or every surfel pruned)")

        facts = {
            "scene": str(scene_dir), "scene_fingerprint": scene.fingerprint(), "preset": cfg.preset, "backend": result.backend, "iterations": result.iterations,
            "surfels_init": result.num_init, "surfels_final": result.params.num,
            "removed_degenerate": result.removed_degenerate, "removed_outside_region": result.removed_outside,
            "surfel_budget": result.surfel_budget, "masks": uses_masks(scene, cfg),
            "final_terms": {k: round(v, 6) for k, v in result.final_terms.items() if isinstance(v, float)},
            "frame": "surfels.ply: world frame, mm (training ran in the normalised frame)",
            "config": asdict(cfg), "loss": asdict(loss),
        }
        write_surfel_ply(tmp / "surfels.ply", result.params, scene.norm_to_world)
        write_splats_3dgs_ply(tmp / "splats_3dgs.ply", result.params, scene.norm_to_world)  # for 3DGS viewers
        (tmp / "train.json").write_text(json.dumps(facts, indent=2, sort_keys=True) + "\n")
    if atomic.written_kind(ckpt) == CHECKPOINT_KIND:
        ckpt.unlink()  # finished: the output is the state now
    return result


def check_side_paths(out_dir: str | Path, inputs, checkpoint: str | Path, live_dir: str | Path | None = None,
                     metrics: str | Path | None = None) -> None:
    """Refuse (one line, before any work) side paths of an optimize run that would lose data
    or fail late: inside the output folder (replaced whole when the run ends), an input or
    inside one, an existing file gcgs did not write (:func:`pipeline.atomic.check_output_file`),
    a curves folder holding files that are not curves (:func:`pipeline.curves.check_curves_dir`)."""
    out = Path(out_dir).resolve()
    for extra in (checkpoint, live_dir, metrics):
        if extra is not None and (Path(extra).resolve() == out or out in Path(extra).resolve().parents):
            raise OutputError(f"{extra}: lies inside the output folder {out_dir}, which is replaced when the run "
                              "ends; put it beside the output")
    atomic.check_output_file(checkpoint, inputs, kind=CHECKPOINT_KIND)
    if metrics is not None:
        atomic.check_output_file(metrics, inputs)
    if live_dir is not None:
        check_curves_dir(live_dir, "train", LOGGED_TERMS, inputs)


def default_side_paths(out_dir: str | Path) -> dict[str, Path]:
    """Where ``gcgs optimize`` puts its checkpoint, timing JSON and curves when not told:
    beside the output, named after it (outside it: the output folder is replaced whole),
    so two outputs never share them."""
    out = Path(out_dir)
    return {"checkpoint": out.parent / f".{out.name}.ckpt.pt", "metrics": out.parent / f"{out.name}.timing.json",
            "live_dir": out.parent / f"{out.name}.curves"}


def timing_report(result: TrainResult, usage: dict, preset: str) -> dict:
    """The run's timings for ``reports/train``: ``usage`` from :func:`pipeline.measure.measure`
    around this process's run, plus the per-part split of every iteration. A resumed run's
    ``wall_s`` and ``cpu_s`` add the training time of the earlier runs (up to the checkpoint
    resumed from), so they are what the whole training cost; ``*_this_run`` are this
    process's alone."""
    iters_run = result.iterations - (result.resumed_from or 0)
    before = result.spent_before
    return {
        **usage, "wall_s": round(usage["wall_s"] + before["wall_s"], 2),
        "cpu_s": round(usage["cpu_s"] + before["cpu_s"], 2),
        "wall_s_this_run": usage["wall_s"], "cpu_s_this_run": usage["cpu_s"],
        "iterations": result.iterations, "iterations_this_run": iters_run, "resumed_from": result.resumed_from,
        # the split is restored from the checkpoint, so it covers every iteration
        "s_per_iteration": round(sum(result.seconds.values()) / max(result.iterations, 1), 4),
        "split_s": {k: round(v, 3) for k, v in result.seconds.items()},
        "surfels_final": result.params.num, "surfel_budget": result.surfel_budget.get("surfels"),
        "backend": result.backend, "preset": preset,
    }
