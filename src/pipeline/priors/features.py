"""Per-view feature maps for the GCF loss (GCGS Eq. 4-9).

Both backends give ``(C, h, w)`` float32 maps at 1/2 resolution (``h = H // 2``,
``w = W // 2``); a feature pixel centre ``j`` sits at image coordinate
``(j + 0.5) * W / w - 0.5`` (= ``2 j + 0.5`` for even W), the convention
``pipeline.losses.sample_features`` samples with.

* ``default``: multi-scale normalised patches. At each scale the grey image's ``k x k``
  patch around the pixel, minus its mean, divided by its norm: the dot product of two
  such vectors is their normalised cross-correlation (NCC), so ``1 - cos`` is ``1 - NCC``,
  invariant to gain and offset changes of the lighting. Scales are concatenated with
  weight ``1/sqrt(S)`` each, so the cosine of two full vectors is the mean NCC over
  scales (the coarse scale widens the loss's basin, the fine one sharpens its minimum).
  Patches whose grey-level standard deviation (after removing their linear ramp, with
  ``detrend``) is below ``min_contrast`` are set to 0 (textureless: no information);
  ``pipeline.losses.gcf_loss`` leaves them out.
* ``vismvsnet``: a user-supplied ONNX export of Vis-MVSNet's feature extractor (the
  32-channel 1/2-resolution level), with Vis-MVSNet's own preprocessing
  (:func:`vismvsnet_input`).
"""
from __future__ import annotations

import cv2
import numpy as np

from pipeline.errors import InputError
from pipeline.onnx_models import OnnxModel

# ImageNet statistics (RGB order).
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)


class FeatureError(InputError):
    """Features that cannot be computed (bad image, non-finite values, no texture)."""


def _check_image(image: np.ndarray, where: str) -> None:
    if image.ndim != 3 or image.shape[2] != 3:
        raise FeatureError(f"{where}: image must be (H, W, 3) RGB, got shape {image.shape}")
    if image.shape[0] < 4 or image.shape[1] < 4:
        raise FeatureError(f"{where}: image {image.shape[1]}x{image.shape[0]} is too small")
    if not np.all(np.isfinite(image)):
        raise FeatureError(f"{where}: image has non-finite values")


def even_crop(image: np.ndarray) -> np.ndarray:
    """Drop the last row/column of odd-sized images, so that the 1/2-resolution grid is
    exact (its pixel ``j`` covers image pixels ``2j, 2j+1``)."""
    H, W = image.shape[:2]
    return image[: H - H % 2, : W - W % 2]


def feature_image_size(height: int, width: int) -> tuple[int, int]:
    """Image size ``(H', W')`` the feature grid refers to (even-cropped); pass it to
    ``pipeline.losses.sample_features`` / ``gcf_loss``."""
    return height - height % 2, width - width % 2


def half_size(height: int, width: int) -> tuple[int, int]:
    """``(h, w)`` of the 1/2-resolution feature map of an ``(H, W)`` image."""
    return height // 2, width // 2


def normalised_patches(grey: np.ndarray, patch: int, dilation: int, min_contrast: float,
                       detrend: bool = False) -> np.ndarray:
    """``(patch^2, h, w)`` mean-subtracted, unit-norm patches of a 2-D image (0 where flat).

    The patch samples ``grey`` at offsets ``dilation * (-r..r)`` (``r = patch // 2``),
    reflecting at the borders. ``detrend``: also remove the patch's least-squares linear
    ramp before the contrast test. NCC cannot place a ramp (smooth shading on a plain
    surface matches its own shifted copy), so a patch that is one carries no information.
    """
    r = patch // 2
    pad = r * dilation
    g = cv2.copyMakeBorder(grey.astype(np.float32), pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
    h, w = grey.shape
    offs = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    out = np.empty((len(offs), h, w), np.float32)
    for c, (dy, dx) in enumerate(offs):
        y0, x0 = pad + dy * dilation, pad + dx * dilation
        out[c] = g[y0:y0 + h, x0:x0 + w]
    out -= out.mean(0, keepdims=True)
    if detrend:  # the x and y ramps over the patch are zero-mean and orthogonal
        for ramp in (np.array([dx for _, dx in offs], np.float32), np.array([dy for dy, _ in offs], np.float32)):
            out -= (np.einsum("chw,c->hw", out, ramp) / (ramp @ ramp))[None] * ramp[:, None, None]
    norm = np.sqrt(np.einsum("chw,chw->hw", out, out))
    # std over the patch = norm / sqrt(n); flat patches carry no information -> 0.
    ok = norm > min_contrast * np.sqrt(len(offs))
    out *= np.where(ok, 1.0 / np.maximum(norm, 1e-12), 0.0)[None]
    return out


def contrast_floor(image: np.ndarray, mask: np.ndarray | None, min_rel_contrast: float) -> float:
    """``min_contrast`` for :func:`default_features` relative to the exposure:
    ``min_rel_contrast`` times the image's mean grey inside ``mask`` (all pixels without
    one), so that a dark capture keeps the features a bright one has (as the MVS's
    ``min_rel_std``)."""
    grey = cv2.cvtColor(np.asarray(image, np.float32), cv2.COLOR_RGB2GRAY)
    inside = grey[mask] if mask is not None and mask.any() else grey
    return float(min_rel_contrast * inside.mean())


def default_features(image: np.ndarray, patch: int = 5, scales: tuple[int, ...] = (1, 2),
                     min_contrast: float = 0.002, detrend: bool = False, where: str = "image") -> np.ndarray:
    """Multi-scale normalised-patch features ``(patch^2 * len(scales), H//2, W//2)``.

    ``image``: ``(H, W, 3)`` RGB in [0, 1]. Scale ``s`` takes patches with dilation ``s``
    on the 1/2-resolution grey image blurred by a Gaussian of sigma ``0.5 * s`` for
    ``s > 1`` (so the coarser samples are not aliased).
    """
    _check_image(image, where)
    if patch < 3 or patch % 2 == 0:
        raise FeatureError(f"feature patch size must be odd and >= 3, got {patch}")
    if not scales or any(int(s) < 1 for s in scales):
        raise FeatureError(f"feature scales must be positive integers, got {scales}")
    grey = cv2.cvtColor(even_crop(image).astype(np.float32), cv2.COLOR_RGB2GRAY)
    h, w = half_size(*grey.shape)
    half = cv2.resize(grey, (w, h), interpolation=cv2.INTER_AREA)  # 2x2 means: centre j at 2j + 0.5
    parts = []
    for s in scales:
        src = half if s == 1 else cv2.GaussianBlur(half, (0, 0), 0.5 * s, borderType=cv2.BORDER_REFLECT_101)
        parts.append(normalised_patches(src, patch, int(s), min_contrast, detrend))
    feats = np.concatenate(parts) / np.float32(np.sqrt(len(parts)))
    if not np.any(feats):
        raise FeatureError(f"{where}: no textured pixel (every patch has contrast below {min_contrast})")
    return feats


def vismvsnet_input(image: np.ndarray) -> np.ndarray:
    """Vis-MVSNet's preprocessing: ``(1, 3, H', W')`` float32, **BGR** channel order,
    ``(x - mean) / std`` with the ImageNet statistics reordered to BGR (Vis-MVSNet reads
    images with OpenCV and applies ``image_net_center``), cropped to even H', W'."""
    x = (even_crop(image) - IMAGENET_MEAN) / IMAGENET_STD
    return np.ascontiguousarray(x[..., ::-1].transpose(2, 0, 1)[None], dtype=np.float32)


def vismvsnet_features(model: OnnxModel, image: np.ndarray, where: str = "image") -> np.ndarray:
    """Run a Vis-MVSNet feature ONNX model: ``(32, H//2, W//2)`` float32."""
    _check_image(image, where)
    H, W = image.shape[:2]
    out = model.run(image=vismvsnet_input(image))["features"][0]
    if out.shape[1:] != half_size(H, W):
        raise FeatureError(
            f"{model.path}: features of {where} have size {out.shape[2]}x{out.shape[1]}, "
            f"expected 1/2 resolution {half_size(H, W)[1]}x{half_size(H, W)[0]}"
        )
    return out.astype(np.float32)
