"""Per-view normal priors n_m for L_nor (GCGS Eq. 10-12).

Our convention (the 2DGS renderer's): unit normals in the OpenCV camera frame of the
view (x right, y down, z forward), oriented towards the camera, ``n . ray < 0``.

* ``default``: from the init stage's depth map: edge-aware (bilateral) smoothing of the
  depth, back-projection, cross product of central differences; the validity mask (Eq.
  10's set M) keeps pixels whose depth and 4 neighbours are valid and which sit at no
  depth discontinuity.
* ``dsine``: a user-supplied DSINE ONNX model (``docs/priors.md``). DSINE's frame is
  (x right, y down, z front) = OpenCV, but its normals point *away* from the camera:
  its RayReLU keeps ``cos(n, ray) > 0`` for the ray ``K^-1 (x, y, 1)``, and a fronto-
  parallel wall is (0, 0, 1). Ours are therefore ``-n_dsine``. DSINE's intrinsics use
  integer pixel centres ("top-left is (0, 0)"), like ours.
"""
from __future__ import annotations

import cv2
import numpy as np

from pipeline import geometry
from pipeline.config.priors import PriorsConfig
from pipeline.errors import InputError
from pipeline.onnx_models import OnnxModel
from pipeline.priors.features import IMAGENET_MEAN, IMAGENET_STD


class NormalError(InputError):
    """Normals that cannot be computed (bad depth, bad model output)."""


def normals_from_depth(depth_mm: np.ndarray, valid: np.ndarray, K: np.ndarray, cfg: PriorsConfig,
                       where: str = "depth") -> tuple[np.ndarray, np.ndarray]:
    """Normals ``(H, W, 3)`` float32 (camera frame, facing the camera) and mask ``(H, W)``.

    Args:
        depth_mm: camera-frame z (mm); ignored where ``valid`` is False.
        K: intrinsics at this size (integer pixel centres).
        cfg: the ``normal_*`` settings:
            ``normal_step_px``: half-width of the central differences (pixels).
            ``normal_smooth_sigma_px``, ``normal_smooth_sigma_mm``: bilateral filter's
            spatial sigma (pixels) and depth sigma (mm); a spatial sigma of 0 disables
            smoothing. Invalid pixels are set to 0 depth first, so the depth sigma keeps
            them (and other surfaces more than a few sigma away) out of the average.
            ``normal_max_slant_deg``: a pixel is at a discontinuity when the depth step
            to a neighbour ``step_px`` away exceeds what a surface slanted by this angle
            to the image plane would give (``tan(angle) * step_px * z / f``); such
            pixels are invalid.
    """
    step_px, max_slant_deg = cfg.normal_step_px, cfg.normal_max_slant_deg
    smooth_sigma_px, smooth_sigma_mm = cfg.normal_smooth_sigma_px, cfg.normal_smooth_sigma_mm
    if depth_mm.ndim != 2 or valid.shape != depth_mm.shape:
        raise NormalError(f"{where}: depth {depth_mm.shape} and valid {valid.shape} must be equal (H, W)")
    valid = valid.astype(bool) & np.isfinite(depth_mm) & (depth_mm > 0)
    if not valid.any():
        raise NormalError(f"{where}: no valid depth pixel")
    z = np.where(valid, depth_mm, 0.0).astype(np.float32)
    if smooth_sigma_px > 0:
        d = int(2 * np.ceil(2 * smooth_sigma_px) + 1)
        z = cv2.bilateralFilter(z, d, float(smooth_sigma_mm), float(smooth_sigma_px))
        z[~valid] = 0.0
    H, W = z.shape
    k = int(step_px)
    rays = geometry.pixel_rays(K, shape=(H, W))
    P = rays * z[..., None]

    def shifted(a, dy, dx, fill):
        out = np.full_like(a, fill)
        out[max(dy, 0):H + min(dy, 0), max(dx, 0):W + min(dx, 0)] = a[max(-dy, 0):H + min(-dy, 0), max(-dx, 0):W + min(-dx, 0)]
        return out

    # Neighbours at +-k: value at (y, x) of shifted(a, -k, 0) is a[y + k, x].
    nb = {(dy, dx): (shifted(P, -dy, -dx, 0.0), shifted(valid, -dy, -dx, False), shifted(z, -dy, -dx, 0.0))
          for dy, dx in ((0, k), (0, -k), (k, 0), (-k, 0))}
    n = np.cross(nb[(k, 0)][0] - nb[(-k, 0)][0], nb[(0, k)][0] - nb[(0, -k)][0])  # dP/dy x dP/dx
    norm = np.linalg.norm(n, axis=-1)
    ok = valid & (norm > 0)
    fpx = 0.5 * (K[0, 0] + K[1, 1])
    max_step = np.tan(np.radians(max_slant_deg)) * k * z / fpx  # mm, per neighbour
    for _, v_n, z_n in nb.values():
        ok &= v_n & (np.abs(z_n - z) <= max_step)
    n = n / np.maximum(norm, 1e-12)[..., None]
    n[np.sum(n * rays, -1) > 0] *= -1  # face the camera
    n[~ok] = 0.0
    return n.astype(np.float32), ok


def dsine_padding(height: int, width: int) -> tuple[int, int, int, int]:
    """``(left, right, top, bottom)`` padding to multiples of 32, split as DSINE does."""
    pw, ph = (-width) % 32, (-height) % 32
    return pw // 2, pw - pw // 2, ph // 2, ph - ph // 2


def dsine_inputs(image: np.ndarray, K: np.ndarray) -> tuple[dict[str, np.ndarray], tuple[int, int, int, int]]:
    """DSINE's inputs for an RGB image in [0, 1] with intrinsics ``K``: the image padded
    with black to multiples of 32 and then ImageNet-normalised (as DSINE's demo), and
    ``K`` with the principal point moved by the padding. Returns ``(inputs, lrtb)``."""
    H, W = image.shape[:2]
    left, r, t, b = dsine_padding(H, W)
    padded = cv2.copyMakeBorder(image.astype(np.float32), t, b, left, r, cv2.BORDER_CONSTANT, value=0.0)
    x = ((padded - IMAGENET_MEAN) / IMAGENET_STD).transpose(2, 0, 1)[None]
    Kp = np.asarray(K, np.float64).copy()
    Kp[0, 2] += left
    Kp[1, 2] += t
    return {"image": np.ascontiguousarray(x, np.float32), "intrinsics": Kp[None].astype(np.float32)}, (left, r, t, b)


def dsine_normals(model: OnnxModel, image: np.ndarray, K: np.ndarray, where: str = "image") -> tuple[np.ndarray, np.ndarray]:
    """Normals ``(H, W, 3)`` float32 in our convention and mask ``(H, W)`` from DSINE.

    Pixels whose raw output is not a unit vector (|n| outside [0.9, 1.1]) or that, after
    the conversion, face away from the camera are invalid.
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise NormalError(f"{where}: image must be (H, W, 3) RGB, got shape {image.shape}")
    H, W = image.shape[:2]
    inputs, (left, _, t, _) = dsine_inputs(image, K)
    out = model.run(**inputs)["normal"][0]  # (3, H+pad, W+pad)
    n_dsine = out[:, t:t + H, left:left + W].transpose(1, 2, 0).astype(np.float64)
    norm = np.linalg.norm(n_dsine, axis=-1)
    n = -n_dsine / np.maximum(norm, 1e-12)[..., None]  # DSINE points away from the camera
    rays = geometry.pixel_rays(K, shape=(H, W))
    ok = (np.abs(norm - 1.0) < 0.1) & (np.sum(n * rays, -1) < 0)
    if not ok.any():
        raise NormalError(f"{model.path}: DSINE output for {where} has no usable normal (not unit length or facing away)")
    n[~ok] = 0.0
    return n.astype(np.float32), ok
