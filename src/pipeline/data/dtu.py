"""Reader and writer for the DTU NeuS/IDR layout.

Layout of a scan directory::

    image/ or images/    000000.png ...   RGB views
    mask/                000.png ...      object masks (optional)
    cameras_sphere.npz or cameras.npz     world_mat_i (DTU projection, world mm -> pixels),
                                          scale_mat_i (unit sphere -> world mm)
    scene.json                            optional metadata written by this package

Views are matched to cameras by the number in the file name (``000023.png`` is view 23,
as in the full 49-view scans where this equals the sorted index). A scan directory may
hold cameras (and masks) for more views than it has images -- the bundled data does,
so held-out views can be used for mask culling. Images whose names are not numbers are
matched to cameras by their sorted index, as NeuS does; only then must the image and
camera counts agree, since nothing else says which camera belongs to which image.
"""
from __future__ import annotations

import json
import re
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline import geometry
from pipeline.atomic import atomic_dir
from pipeline.data.scene import Scene, SceneError

IMAGE_DIRS = ("image", "images")
CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
DEFAULT_VIEWS = (23, 24, 33)


@dataclass
class DTUCameras:
    """All cameras of a scan, at the resolution of the stored images."""

    K: dict[int, np.ndarray]  # view id -> 3x3 intrinsics
    world_to_cam: dict[int, np.ndarray]  # view id -> 4x4 world(mm) -> camera
    norm_to_world: np.ndarray  # 4x4 scale_mat
    path: Path

    @property
    def ids(self) -> list[int]:
        return sorted(self.K)


def _numbered_files(folder: Path, exts=IMAGE_EXTS) -> dict[int, Path]:
    """Files of ``folder`` by view id: the number in the name, or (when some name is not
    a number) the sorted index, as NeuS does (see :func:`_named_by_number`)."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in exts)
    if not _named_by_number(files):
        return dict(enumerate(files))
    out: dict[int, Path] = {}
    for p in files:
        key = int(p.stem)
        if key in out:
            raise SceneError(f"{p}: two files in {folder} are numbered {key}")
        out[key] = p
    return out


def _named_by_number(files) -> bool:
    return all(re.fullmatch(r"\d+", p.stem) for p in files)


def find_image_dir(root: Path) -> Path:
    if not root.is_dir():
        raise SceneError(f"{root}: scene directory not found")
    for name in IMAGE_DIRS:
        if (root / name).is_dir():
            return root / name
    raise SceneError(f"{root}: no image directory (expected one of {', '.join(IMAGE_DIRS)}/)")


def find_camera_file(root: Path) -> Path:
    for name in CAMERA_FILES:
        if (root / name).is_file():
            return root / name
    raise SceneError(f"{root}: no camera file (expected {' or '.join(CAMERA_FILES)})")


def read_image(path: Path) -> np.ndarray:
    """RGB float32 in [0, 1]; a clear error for unreadable, truncated or corrupt files."""
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    _check_whole(path)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None or img.size == 0:
        raise SceneError(f"{path}: not a readable image (corrupt or unsupported format)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def read_mask(path: Path) -> np.ndarray:
    """Foreground where the grey value is > 127; in an image with an alpha channel that is
    not constant (the mask exported as transparency) where the alpha is > 127."""
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    alpha = _check_whole(path, alpha=True)
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None or m.size == 0:
        raise SceneError(f"{path}: not a readable mask image (corrupt or unsupported format)")
    if alpha is not None and alpha.min() != alpha.max():
        return alpha > 127
    return m > 127


def _check_whole(path: Path, alpha: bool = False) -> np.ndarray | None:
    """Read ``path`` to its end with PIL, which raises on a file cut short or corrupt where
    cv2 may only warn and fill in grey ("Premature end of JPEG file"); cv2 still decodes the
    pixels. Returns the 8-bit alpha channel when ``alpha`` and the image has one."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            if alpha and ("A" in im.getbands() or (im.mode in ("P", "L", "RGB") and "transparency" in im.info)):
                return np.asarray(im.convert("RGBA").getchannel("A"))
            if im.format == "PNG":
                im.verify()  # every chunk there with its checksum, without inflating: cheap
                return None
            if im.format == "JPEG":  # DCT scaling: all the data is still read, 1/64 of the pixels made
                im.draft(im.mode, (max(1, im.width // 8), max(1, im.height // 8)))
            im.load()
    except UnidentifiedImageError:
        return None  # a format PIL does not know: cv2's decode is the only check
    except (OSError, SyntaxError, ValueError) as exc:
        raise SceneError(f"{path}: image file is truncated or corrupt ({exc})") from exc
    return None


def scale_mat_problem(S: np.ndarray) -> str | None:
    """Why ``S`` cannot be a scan's ``scale_mat`` (unit sphere -> world), or ``None``; shared
    by the reader and by ``gcgs prepare --sphere``, so prepare writes no scene the reader refuses."""
    S = np.asarray(S, dtype=np.float64)
    if S.shape != (4, 4) or not np.all(np.isfinite(S)):
        return f"must be a finite 4x4 matrix, got shape {S.shape}"
    if abs(np.linalg.det(S)) < 1e-12:
        return "is singular"
    return None


def load_cameras(root: str | Path) -> DTUCameras:
    """Read every ``world_mat_i``/``scale_mat_i`` pair of a scan and decompose it."""
    root = Path(root)
    path = find_camera_file(root)
    try:
        data = np.load(path)
        files = list(data.files)
    except Exception as exc:  # zipfile/pickle errors vary; name the file.
        raise SceneError(f"{path}: cannot read camera file ({exc})") from exc
    ids = sorted(int(m.group(1)) for k in files if (m := re.fullmatch(r"world_mat_(\d+)", k)))
    if not ids:
        raise SceneError(f"{path}: no world_mat_i entries")
    K, w2c = {}, {}
    scale = None
    for i in ids:
        P = np.asarray(data[f"world_mat_{i}"], dtype=np.float64)
        try:
            K[i], w2c[i] = geometry.decompose_projection(P)
        except geometry.CameraError as exc:
            raise SceneError(f"{path}: world_mat_{i}: {exc}") from exc
        key = f"scale_mat_{i}"
        if key not in files:
            raise SceneError(f"{path}: missing {key}")
        S = np.asarray(data[key], dtype=np.float64)
        if problem := scale_mat_problem(S):
            raise SceneError(f"{path}: {key} {problem}")
        if scale is None:
            scale = S
        elif not np.allclose(S, scale, rtol=1e-5, atol=1e-6):
            raise SceneError(f"{path}: {key} differs from scale_mat_{ids[0]}; one normalisation per scan is required")
    return DTUCameras(K=K, world_to_cam=w2c, norm_to_world=scale, path=path)


def read_meta(root: Path) -> dict:
    p = root / "scene.json"
    if not p.is_file():
        return {}
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError as exc:
        raise SceneError(f"{p}: invalid JSON ({exc})") from exc


def prepared_views(scene: str | Path) -> list[int] | None:
    """The input views ``gcgs prepare`` made ``scene`` with (its scene.json ``views``); ``None``
    for a scene that records none (a source scan such as ``gcgs synth``'s output)."""
    views = read_meta(Path(scene)).get("views")
    if views is not None and not (isinstance(views, list) and views
                                  and all(type(v) is int and v >= 0 for v in views)):
        raise SceneError(f"{Path(scene) / 'scene.json'}: views must be a list of view ids, got {views!r}")
    return views


def load_scene(
    root: str | Path,
    view_ids: list[int] | tuple[int, ...] | None = DEFAULT_VIEWS,
    resolution: tuple[int, int] | None = None,
    with_masks: bool = True,
    name: str | None = None,
) -> Scene:
    """Load a DTU-layout scan.

    Args:
        root: scan directory.
        view_ids: views to load (``None``: every view with an image).
        resolution: ``(width, height)`` to resize to; ``None`` keeps the stored size.
            Intrinsics are scaled with the integer-pixel-centre convention.
        with_masks: read ``mask/`` when present (an absent folder gives ``masks=None``).
    """
    root = Path(root)
    image_dir = find_image_dir(root)
    image_files = _numbered_files(image_dir)
    if not image_files:
        raise SceneError(f"{image_dir}: no images ({'/'.join(IMAGE_EXTS)})")
    cams = load_cameras(root)
    if not _named_by_number(image_files.values()) and len(cams.ids) != len(image_files):
        raise SceneError(
            f"{cams.path}: camera count ({len(cams.ids)}) does not match image count "
            f"({len(image_files)}) in {image_dir}, whose names are not view numbers (so images "
            "are matched to cameras by sorted index)"
        )
    missing = [i for i in image_files if i not in cams.K]
    if missing:
        raise SceneError(f"{cams.path}: no world_mat for image(s) {missing[:5]} in {image_dir}")
    ids = sorted(image_files) if view_ids is None else [int(v) for v in view_ids]
    for v in ids:
        if v not in image_files:
            raise SceneError(f"{image_dir}: view {v} requested but no such image (have {sorted(image_files)[:8]}...)")

    mask_dir = root / "mask"
    mask_files = _numbered_files(mask_dir) if (with_masks and mask_dir.is_dir()) else None

    images, masks, Ks, w2cs = [], [], [], []
    size = None
    for v in ids:
        img = read_image(image_files[v])
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        elif (w, h) != size:
            raise SceneError(f"{image_files[v]}: size {w}x{h} differs from the other views ({size[0]}x{size[1]})")
        K = cams.K[v]
        if mask_files is not None:
            if v not in mask_files:
                raise SceneError(f"{mask_dir}: no mask for view {v}")
            m = read_mask(mask_files[v])
            if m.shape != (h, w):
                raise SceneError(f"{mask_files[v]}: mask size {m.shape[1]}x{m.shape[0]} differs from image size {w}x{h}")
            if not m.any():
                raise SceneError(f"{mask_files[v]}: mask is empty (no foreground pixel)")
        if resolution is not None and tuple(resolution) != (w, h):
            W, H = int(resolution[0]), int(resolution[1])
            if W <= 0 or H <= 0:
                raise SceneError(f"invalid resolution {resolution}")
            K = geometry.scale_intrinsics(K, W / w, H / h)
            interp = cv2.INTER_AREA if W < w else cv2.INTER_LINEAR
            img = cv2.resize(img, (W, H), interpolation=interp)
            if mask_files is not None:
                m = resize_mask(m, W, H)
        images.append(img)
        Ks.append(K)
        w2cs.append(cams.world_to_cam[v])
        if mask_files is not None:
            masks.append(m)

    meta = read_meta(root)
    scan_id = meta.get("scan_id")
    if scan_id is None and (m := re.fullmatch(r"scan(\d+)", root.name)):
        scan_id = int(m.group(1))  # DTU folders are named scanNN
    return Scene(
        name=name or meta.get("name") or root.name,
        images=np.stack(images).astype(np.float32),
        masks=np.stack(masks) if mask_files is not None else None,
        K=np.stack(Ks),
        world_to_cam=np.stack(w2cs),
        norm_to_world=cams.norm_to_world,
        view_ids=ids,
        source=root,
        scan_id=scan_id,
        meta=meta,
    )


def _write_png(path: Path, rgb_or_gray: np.ndarray) -> None:
    arr = rgb_or_gray
    if arr.dtype != np.uint8:
        arr = np.clip(np.round(arr * 255.0), 0, 255).astype(np.uint8)
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    if not cv2.imwrite(str(path), arr):
        raise OSError(f"{path}: could not write image")


def write_scene(
    out_dir: str | Path,
    images: dict[int, np.ndarray],
    K: dict[int, np.ndarray],
    world_to_cam: dict[int, np.ndarray],
    norm_to_world: np.ndarray,
    masks: dict[int, np.ndarray] | None = None,
    meta: dict | None = None,
    inputs: tuple[str | Path, ...] = (),
) -> Path:
    """Write a scan in the DTU layout as a gcgs ``scene`` output (:func:`pipeline.atomic.atomic_dir`:
    checked against ``inputs``, complete or not at all). Arguments as :func:`write_scene_files`."""
    out_dir = Path(out_dir)
    with atomic_dir(out_dir, "scene", inputs) as tmp:
        write_scene_files(tmp, images, K, world_to_cam, norm_to_world, masks, meta)
    return out_dir


def write_scene_files(
    folder: Path,
    images: dict[int, np.ndarray],
    K: dict[int, np.ndarray],
    world_to_cam: dict[int, np.ndarray],
    norm_to_world: np.ndarray,
    masks: dict[int, np.ndarray] | None = None,
    meta: dict | None = None,
) -> None:
    """Write a scan's files into the existing ``folder`` (a caller's atomic temporary folder).

    ``images``/``masks`` map view id to an RGB float/uint8 image or a bool mask.
    Cameras may cover more views than ``images`` (held-out views).
    """
    (folder / "image").mkdir()
    for v, img in images.items():
        _write_png(folder / "image" / f"{v:06d}.png", img)
    if masks:
        (folder / "mask").mkdir()
        for v, m in masks.items():
            _write_png(folder / "mask" / f"{v:03d}.png", np.asarray(m, dtype=np.uint8) * 255)
    cams = {}
    for v in sorted(K):
        cams[f"world_mat_{v}"] = geometry.compose_projection(K[v], world_to_cam[v])
        cams[f"scale_mat_{v}"] = np.asarray(norm_to_world, dtype=np.float64)
    np.savez(folder / "cameras_sphere.npz", **cams)
    if meta is not None:
        (folder / "scene.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


def first_image(root: str | Path) -> Path:
    """The image of a scan's lowest view id."""
    files = _numbered_files(find_image_dir(Path(root)))
    if not files:
        raise SceneError(f"{root}: no images")
    return files[min(files)]


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of an image file, from its header."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size
    except (OSError, SyntaxError, ValueError) as exc:
        raise SceneError(f"{path}: not a readable image ({exc})") from exc


def stored_image_size(root: str | Path) -> tuple[int, int]:
    """``(width, height)`` of the stored images of a scan: the size its cameras are for, so
    every image must have it. An image of another size is an error naming it (the size
    most images have is taken as the scan's)."""
    files = _numbered_files(find_image_dir(Path(root)))
    if not files:
        raise SceneError(f"{root}: no images")
    sizes = {p: image_size(p) for p in files.values()}
    common = Counter(sizes.values()).most_common(1)[0][0]
    for p, size in sizes.items():
        if size != common:
            raise SceneError(f"{p}: size {size[0]}x{size[1]} differs from the scan's other images "
                             f"({common[0]}x{common[1]}); every image must have the size its camera is for")
    return common


def resize_mask(mask: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-resample a bool mask (foreground where more than half the area is)."""
    if mask.shape == (height, width):
        return mask
    interp = cv2.INTER_AREA if width < mask.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(mask.astype(np.float32), (width, height), interpolation=interp) > 0.5


def load_masks(root: str | Path, view_ids: list[int] | None = None,
               size: tuple[int, int] | None = None) -> dict[int, np.ndarray]:
    """Masks of a scan by view id (all of them by default), at their stored size, or at
    ``size`` ``(width, height)``: then a mask of another aspect ratio is an error naming it
    (resizing would squash it)."""
    mask_dir = Path(root) / "mask"
    if not mask_dir.is_dir():
        raise SceneError(f"{root}: no mask/ directory")
    files = _numbered_files(mask_dir)
    ids = sorted(files) if view_ids is None else list(view_ids)
    out = {}
    for v in ids:
        if v not in files:
            raise SceneError(f"{mask_dir}: no mask for view {v}")
        m = read_mask(files[v])
        if size is not None:
            h, w = m.shape
            if abs(size[1] - size[0] * h / w) >= 1.0:
                raise SceneError(f"{files[v]}: mask is {w}x{h} (aspect {w / h:.3f}) but the images are "
                                 f"{size[0]}x{size[1]} (aspect {size[0] / size[1]:.3f}); resizing would squash it")
            m = resize_mask(m, *size)
        out[v] = m
    return out


def image_ids(root: str | Path) -> list[int]:
    """Sorted view ids of the images of a scan."""
    return sorted(_numbered_files(find_image_dir(Path(root))))
