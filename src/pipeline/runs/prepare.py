"""The prepare stage from files to files, with the masks a capture without masks needs
(docs/inputs.md, "Without masks"): a capture -> a prepared scene whose masks are the
capture's own, derived here, or none.

``masks``:

* ``auto`` (the default): the capture's masks when it has them, else derived;
* ``capture``: the capture's masks (refused when it has none);
* ``derive``: derived even where the capture has masks (they are left out first): the scene
  is prepared into a temporary folder, the init's ``mvs`` backend runs on it in memory, and
  :func:`pipeline.runs.masks.derive_scene_masks` writes the final scene with ``mask/`` and
  ``"masks": "derived"``, so the usual stages (init, priors, optimize, mesh) run on it with
  no second pass;
* ``none``: no masks (the method then models the table and background).
"""
from __future__ import annotations

import tempfile
from collections.abc import Callable
from pathlib import Path

from pipeline.config.data import DataConfig
from pipeline.config.init import InitConfig
from pipeline.config.mesh import MeshConfig
from pipeline.data import layouts
from pipeline.data.prepare import prepare_scene
from pipeline.data.scene import Scene, SceneError
from pipeline.errors import print_warning
from pipeline.runs.masks import derive_scene_masks

MASKS = ("auto", "capture", "derive", "none")


def capture_has_masks(src: str | Path) -> bool:
    """Whether the capture brings masks for its views (any layout)."""
    src = Path(src)
    if layouts.detect(src) == "dtu":
        return (src / "mask").is_dir()
    return layouts.read_capture(src).masks is not None


def prepare_with_masks(src: str | Path, out: str | Path, cfg: DataConfig, masks: str, init_cfg: InitConfig,
                       mesh_cfg: MeshConfig, name: str | None = None,
                       sphere: tuple[float, float, float, float] | None = None,
                       warn: Callable[[str], None] = print_warning) -> tuple[Scene | None, dict | None]:
    """Prepare ``src`` into ``out`` with ``masks`` (module docstring). Returns the prepared
    scene (``None`` when its masks were derived: load ``out``) and the ``derived_masks``
    record (``None`` unless derived)."""
    if masks not in MASKS:
        raise SceneError(f"--masks must be one of {', '.join(MASKS)}, got {masks!r}")
    has = capture_has_masks(src)
    if masks == "capture" and not has:
        raise SceneError(f"{src}: the capture has no masks (use --masks derive or --masks none)")
    if masks in ("capture", "none") or (masks == "auto" and has):
        return prepare_scene(src, out, cfg, name=name, use_masks=masks != "none", sphere=sphere, warn=warn), None
    with tempfile.TemporaryDirectory(prefix="gcgs-prepare-") as tmp:
        plain = Path(tmp) / "scene"
        prepare_scene(src, plain, cfg, name=name, use_masks=False, sphere=sphere, warn=warn)
        record = derive_scene_masks(plain, None, out, mesh_cfg, init_cfg=init_cfg, warn=warn,
                                    inputs=(src,), source=str(src))
    return None, record
