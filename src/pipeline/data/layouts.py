"""Which layout a source folder has, known by its files: DTU NeuS/IDR (``cameras_sphere.npz``
or ``cameras.npz``), COLMAP (``images/`` + ``sparse/0/`` or ``sparse/``) or nerfstudio
(``transforms.json``); docs/inputs.md. DTU scans are read by :mod:`pipeline.data.dtu`,
the others into a :class:`pipeline.data.capture.Capture`."""
from __future__ import annotations

from pathlib import Path

from pipeline.data import colmap, dtu, nerfstudio
from pipeline.data.capture import Capture
from pipeline.data.scene import SceneError

LAYOUTS = ("dtu", "colmap", "nerfstudio")


def detect(src: str | Path) -> str:
    """The layout of ``src``; a folder of none of them is an error saying what each needs."""
    root = Path(src)
    if not root.is_dir():
        raise SceneError(f"{root}: scene directory not found")
    if any((root / name).is_file() for name in dtu.CAMERA_FILES):
        return "dtu"
    if colmap.is_colmap(root):
        return "colmap"
    if nerfstudio.is_nerfstudio(root):
        return "nerfstudio"
    if any((root / name).is_dir() for name in dtu.IMAGE_DIRS) and not (root / "sparse").is_dir():
        return "dtu"  # the DTU reader names the missing camera file
    if (root / "sparse").is_dir():
        raise SceneError(f"{root}: a COLMAP folder needs images/ and a model in sparse/0/ or sparse/ "
                         "(cameras, images, points3D as .txt or .bin)")
    raise SceneError(f"{root}: not a known capture layout: expected a DTU scan (image/, "
                     f"{' or '.join(dtu.CAMERA_FILES)}), a COLMAP folder (images/, sparse/0/) or a nerfstudio "
                     f"folder ({nerfstudio.FILE}); see docs/inputs.md")


def read_capture(src: str | Path) -> Capture:
    """A COLMAP or nerfstudio capture (a DTU scan is read by :mod:`pipeline.data.dtu`)."""
    layout = detect(src)
    if layout == "colmap":
        return colmap.read_capture(src)
    if layout == "nerfstudio":
        return nerfstudio.read_capture(src)
    raise ValueError(f"{src}: a DTU scan is read by pipeline.data.dtu")


def image_dir(src: str | Path) -> Path:
    """Where ``src``'s images are (named in messages)."""
    layout = detect(src)
    if layout == "dtu":
        return dtu.find_image_dir(Path(src))
    return Path(src) / "images" if layout == "colmap" else Path(src)


def stored_image_size(src: str | Path) -> tuple[int, int]:
    """``(width, height)`` the cameras of ``src`` are for (every view has it)."""
    if detect(src) == "dtu":
        return dtu.stored_image_size(src)
    return read_capture(src).size
