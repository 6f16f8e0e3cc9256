"""The masks stage from files to files: a prepared scene without masks (and the init folder
computed on it, or the init's MVS run here) -> a copy of the scene with object masks derived
per input view (:func:`pipeline.labelling.label_scene`, :func:`pipeline.masks.derive_masks`)
in ``mask/``, marked ``"masks": "derived"`` in its ``scene.json``, and optionally an overlay
picture per view (docs/inputs.md, "Derived masks").

Given masks always win: a scene that has ``mask/`` is refused, since every stage already
uses its masks. The copy is byte for byte (images, cameras, anything else the folder holds)
but for ``scene.json``, which gains the ``masks`` marker and a ``derived_masks`` record,
and the new ``mask/`` (the format ``gcgs prepare`` writes: 8-bit grey PNGs, 255 on the
object, ``NNN.png`` by view id).
"""
from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from pipeline import atomic
from pipeline import labelling
from pipeline import masks as derive
from pipeline.config.init import InitConfig
from pipeline.config.mesh import MeshConfig
from pipeline.data import dtu
from pipeline.data.scene import SceneError, check_made_from, check_scene
from pipeline.errors import DegenerateResultError, MissingInputError, OutputError, print_warning
from pipeline.init.backends import run_backend
from pipeline.init.io import load_init_depths, stacked_depths_mm

DERIVED = "derived"  # scene.json "masks" of a scene written here; a scene with given masks has no such key


def mask_path(folder: Path, view: int) -> Path:
    """Where a prepared scene keeps view ``view``'s mask (:func:`pipeline.data.dtu.write_scene_files`)."""
    return folder / "mask" / f"{int(view):03d}.png"


def overlay_path(folder: Path, view: int) -> Path:
    return folder / f"{int(view):03d}.png"


def check_scene_without_masks(scene_dir: Path) -> None:
    """Refuse (one line) a scene that has masks: given masks always win, and derived ones
    are already there."""
    if not (scene_dir / "mask").is_dir():
        return
    if dtu.read_meta(scene_dir).get("masks") == DERIVED:
        raise SceneError(f"{scene_dir}: the scene already has derived masks (scene.json masks: derived); "
                         "run the stages (init, priors, optimize, mesh) on it")
    raise SceneError(f"{scene_dir}: the scene has masks (mask/), and given masks always win: run the stages on it "
                     "as it is; gcgs masks is for a scene without masks")


def derive_scene_masks(scene_dir: str | Path, init_dir: str | Path | None, out_scene: str | Path, cfg: MeshConfig,
                       overlays_dir: str | Path | None = None, warn: Callable[[str], None] = print_warning,
                       init_cfg: InitConfig | None = None, model: str | Path | None = None,
                       inputs: tuple = (), source: str | None = None) -> dict:
    """Files to files (module docstring): ``scene_dir`` (no ``mask/``) and ``init_dir`` (its
    depth maps; ``None``: the init's ``mvs`` backend with ``init_cfg`` runs here, in memory)
    -> ``out_scene``, a gcgs ``scene`` output, and, with ``overlays_dir``, a gcgs
    ``mask-overlays`` output of :func:`pipeline.masks.overlay` per view. The labelling uses
    the mesh stage's settings (``cfg``: ``voxel_norm``, ``region_plane_margin_norm``).
    ``model``: a salient-object ONNX model refining inside the band
    (:class:`pipeline.masks.SaliencyModel`). Each fallback of a view is one ``warn`` line
    naming the view and the failed test. Every check runs before anything is written, and
    both outputs appear complete or not at all. Returns the ``derived_masks`` record written
    to the new ``scene.json``."""
    scene_dir = Path(scene_dir)
    dtu.find_image_dir(scene_dir)  # a scene folder at all (one line naming it if not)
    check_scene_without_masks(scene_dir)
    if init_dir is not None and not Path(init_dir).is_dir():
        raise MissingInputError(f"{init_dir}: init folder not found (run gcgs init --scene {scene_dir} "
                                f"--out-dir {init_dir} first, or leave --init-dir out to run its MVS here)")
    if overlays_dir is not None and any(atomic.overlapping_inputs(atomic.resolved_path(overlays_dir), (out_scene,))):
        raise OutputError(f"{overlays_dir}: the overlays folder and the new scene {out_scene} must not hold one "
                          "another (each is replaced whole): choose separate folders")
    saliency = derive.SaliencyModel(model) if model is not None else None
    inputs = tuple(x for x in (scene_dir, init_dir, model, *inputs) if x is not None)
    with ExitStack() as outputs:
        overlays_tmp = None
        if overlays_dir is not None:
            overlays_tmp = outputs.enter_context(atomic.atomic_dir(overlays_dir, "mask-overlays", inputs=inputs))
        tmp = outputs.enter_context(atomic.atomic_dir(out_scene, "scene", inputs=inputs))
        scene = dtu.load_scene(scene_dir, view_ids=None)
        check_scene(scene, min_views=2, needed_by="gcgs masks")
        if init_dir is not None:
            check_made_from(scene, init_dir, "init.json", "init")
            depths = stacked_depths_mm(load_init_depths(init_dir, scene, needed_by="gcgs masks"))
        else:
            init_cfg = InitConfig.default() if init_cfg is None else init_cfg
            depths = stacked_depths_mm(run_backend("mvs", scene, init_cfg).depths)
        scale = scene.norm_scale_mm
        labels = labelling.label_scene(depths, scene.K, scene.world_to_cam, scene.norm_to_world, cfg.voxel_norm * scale,
                                       cfg.region_plane_margin_norm * scale)
        results = derive.derive_masks(scene.images, scene.K, scene.world_to_cam, depths, labels, scene.view_ids,
                                      saliency=saliency)
        for r in results:
            if not r.mask.any():  # the fallback too is empty: a scene no stage can use
                raise DegenerateResultError(
                    f"{scene_dir}: view {r.view}: neither the derived mask nor the region's silhouette covers a pixel "
                    f"(the object's sphere is outside the view); nothing written to {out_scene}")
        for r in results:
            for w in r.warnings:
                warn(f"{scene_dir}: {w}")

        shutil.copytree(scene_dir, tmp, dirs_exist_ok=True,
                        ignore=lambda d, names: [n for n in names if Path(d) == scene_dir
                                                 and n in ("scene.json", atomic.MARKER, atomic.PARTIAL)])
        (tmp / "mask").mkdir()
        for r in results:
            dtu._write_png(mask_path(tmp, r.view), r.mask.astype(np.uint8) * 255)  # as prepare writes masks
        record = {"scene": source or str(scene_dir), "init_dir": None if init_dir is None else str(init_dir),
                  "model": None if model is None else str(model), "region": labels.region.facts(),
                  "table_found": labels.plane is not None, "footprint_found": labels.region.footprint is not None,
                  "labelling": labels.facts,
                  "views": {str(r.view): {"coverage": round(r.coverage, 4), "method": r.method,
                                          **({"warning": r.warnings[0]} if r.warnings else {})} for r in results}}
        meta = {**dtu.read_meta(scene_dir), "masks": DERIVED, "derived_masks": record}
        (tmp / "scene.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        if overlays_tmp is not None:
            for r, image in zip(results, scene.images):
                dtu._write_png(overlay_path(overlays_tmp, r.view), derive.overlay(image, r.mask))
    return record
