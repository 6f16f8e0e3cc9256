"""The priors stage from files to files: per-view normals and features of a prepared scene
in a gcgs ``priors`` folder (docs/priors.md)."""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path

from pipeline.atomic import atomic_dir
from pipeline.config.loss import LossConfig
from pipeline.config.priors import PriorsConfig
from pipeline.data.dtu import load_scene
from pipeline.data.scene import check_made_from, check_scene
from pipeline.errors import ConfigError
from pipeline.init.io import load_init_depths
from pipeline.onnx_models import DSINE_CONTRACT, VISMVSNET_FEATURES_CONTRACT, load_onnx
from pipeline.priors import features as feat, normals as nrm
from pipeline.priors.io import (
    FeaturePrior,
    NormalPrior,
    features_path,
    normals_path,
    write_features,
    write_normals,
)


def effective_backends(cfg: PriorsConfig, losses: Sequence[LossConfig]) -> tuple[str, str]:
    """``(normals, features)`` backends actually run: ``none`` where every loss setting that
    trains on these priors (the main one and the ablation cells', ``config.losses_in_use``)
    weights the prior 0."""
    return (cfg.normals if any(loss.lambda_nor > 0 for loss in losses) else "none",
            cfg.features if any(loss.lambda_gcf > 0 for loss in losses) else "none")


def run_priors(scene_dir: str | Path, out_dir: str | Path, cfg: PriorsConfig, losses: Sequence[LossConfig],
               init_dir: str | Path | None = None) -> dict:
    """Compute the configured priors of every view and write them atomically; returns
    the facts written to priors.json (no timings: identical inputs give identical bytes)."""
    out_dir = Path(out_dir)
    normals_backend, features_backend = effective_backends(cfg, losses)
    models = (cfg.dsine_model if normals_backend == "dsine" else None,
              cfg.vismvsnet_model if features_backend == "vismvsnet" else None)
    with atomic_dir(out_dir, "priors", inputs=(scene_dir, init_dir, *models)) as tmp:
        scene = load_scene(scene_dir, view_ids=None)
        check_scene(scene)
        # Everything that can fail on bad input is checked before any output is written.
        if init_dir is not None:
            check_made_from(scene, init_dir, "init.json", "init")
        depths = None
        if normals_backend == "default":
            if init_dir is None:
                raise ConfigError("priors.normals = default needs the init stage's depth maps: pass --init-dir "
                                  "(or set priors.normals to dsine or none)")
            depths = load_init_depths(init_dir, scene, needed_by="priors.normals = default")
        dsine = load_onnx(cfg.dsine_model, DSINE_CONTRACT) if normals_backend == "dsine" else None
        vis = load_onnx(cfg.vismvsnet_model, VISMVSNET_FEATURES_CONTRACT) if features_backend == "vismvsnet" else None
        per_view = {}
        for i, v in enumerate(scene.view_ids):
            where = f"{scene.source} view {v}"
            facts = {}
            if normals_backend != "none":
                if normals_backend == "default":
                    d = depths[i]
                    n, ok = nrm.normals_from_depth(d.depth_mm, d.valid, scene.K[i], cfg, where=where)
                else:
                    n, ok = nrm.dsine_normals(dsine, scene.images[i], scene.K[i], where=where)
                write_normals(normals_path(tmp, v), NormalPrior(v, n, ok, normals_backend))
                facts["normals_valid_fraction"] = round(float(ok.mean()), 4)
            if features_backend != "none":
                if features_backend == "default":
                    f = feat.default_features(scene.images[i], patch=cfg.feature_patch,
                                              scales=tuple(cfg.feature_scales),
                                              min_contrast=feat.contrast_floor(
                                                  scene.images[i], None if scene.masks is None else scene.masks[i],
                                                  cfg.feature_min_rel_contrast),
                                              detrend=cfg.feature_detrend, where=where)
                else:
                    f = feat.vismvsnet_features(vis, scene.images[i], where=where)
                size = feat.feature_image_size(scene.height, scene.width)
                write_features(features_path(tmp, v), FeaturePrior(v, f, size, features_backend), cfg.feature_dtype)
                facts["feature_shape"] = list(f.shape)
            per_view[str(v)] = facts
        info = {
            "scene": str(scene_dir),
            "scene_fingerprint": scene.fingerprint(),
            "init_dir": str(init_dir) if init_dir else None,
            "views": scene.view_ids,
            "size": [scene.width, scene.height],
            "normals": normals_backend,
            "features": features_backend,
            "per_view": per_view,
            "config": dataclasses.asdict(cfg),
        }
        (tmp / "priors.json").write_text(json.dumps(info, indent=2, sort_keys=True) + "\n")
    return info
