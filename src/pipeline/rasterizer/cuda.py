"""The ``cuda`` backend: gsplat's ``rasterization_2dgs`` mapped onto ``RenderOutput``.

gsplat is imported lazily (installing it pulls a CUDA build of torch; it is not a
dependency of this package). Mapping and known differences (docs/rasterizer.md):

* pixel centres: gsplat puts them at ``+0.5``, so ``cx, cy`` are shifted by 0.5;
* skew: gsplat's 2DGS projection reads ``fx, fy, cx, cy`` alone and drops ``K[0, 1]``, so a
  camera whose skew moves a pixel by more than ``MAX_SKEW_SHIFT_PX`` is refused (DTU's
  moves none by more than 1e-4 px);
* depth: gsplat composites the surfel *centre* depth ``z_c`` per surfel, not the
  ray–splat intersection: ``depth_expected = sum w z_c / (sum w + eps)`` and
  ``depth_median`` is the median surfel's ``z_c``;
* distortion: gsplat's own is an L1 form on ``z_c``; instead the 2DGS L2 distortion is
  rebuilt from two extra channels, ``sum w dm`` and ``sum w dm^2`` with
  ``dm = m(z_c) - m_ref``: ``distortion = A M2 - M1^2`` (an exact identity; ``m_ref``, a
  per-image constant, only reduces float32 cancellation);
* alpha cap 0.999 (ours 0.99), stop when ``T <= 1e-4`` (ours ``< 1e-4``), no per-pixel
  near-plane skip, low-pass centre = centre of the 3-sigma bounding box;
* ``means2d``: the AABB centres (shifted to integer pixel centres); its ``.grad`` is
  gsplat's densification gradient ``(dL/dT_02, dL/dT_12) * z_c``.
"""
from __future__ import annotations

import torch

from pipeline.rasterizer.project import colors_of
from pipeline.rasterizer.types import Camera, RenderOutput, Surfels

# The largest shift (px) that gsplat's dropping of the skew may cause anywhere in the image.
MAX_SKEW_SHIFT_PX = 0.01


def skew_shift_px(camera: Camera) -> float:
    """How far (px) the skew ``K[0, 1]`` moves a pixel of ``camera``'s image at most:
    ``|s| |v - cy| / fy`` over the rows ``v``."""
    K = camera.K
    rows = max(abs(float(K[1, 2])), abs(camera.height - 1 - float(K[1, 2])))
    return abs(float(K[0, 1])) * rows / float(K[1, 1])


def rasterize(surfels: Surfels, camera: Camera, *, depth_eps: float) -> RenderOutput:
    """Render on the GPU. Surfels on the CPU are copied there (differentiably) and every
    map comes back to the CPU, so a trainer whose losses run on the CPU uses this backend
    unchanged; surfels on a CUDA device stay there."""
    shift = skew_shift_px(camera)
    if shift > MAX_SKEW_SHIFT_PX:
        raise ValueError(
            f"the cuda backend (gsplat) ignores the camera's skew K[0, 1] = {float(camera.K[0, 1]):.4g}, which moves "
            f"pixels by up to {shift:.3g} px here (> {MAX_SKEW_SHIFT_PX} px): use the cpu backend for this camera"
        )
    if not torch.cuda.is_available():
        raise ValueError("the cuda backend needs a CUDA device; none is available")
    try:
        from gsplat import rasterization_2dgs
    except ImportError as exc:
        raise ValueError("the cuda backend needs gsplat (pip install gsplat with a CUDA torch)") from exc
    if surfels.means.dtype != torch.float32:
        raise ValueError(f"the cuda backend needs float32 tensors, got {surfels.means.dtype}")
    home = surfels.means.device
    if home.type != "cuda":
        surfels = Surfels(*(t.to("cuda") for t in (surfels.means, surfels.quats, surfels.scales, surfels.opacities,
                                                   surfels.features)), surfels.sh_degree)
    dev = surfels.means.device
    w2c = camera.world_to_cam.to(dev, torch.float32)
    K = camera.K.clone()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    K = K.to(dev, torch.float32)
    near, far = camera.near, camera.far

    colors = colors_of(surfels, camera)
    C = colors.shape[1]
    z_c = surfels.means @ w2c[2, :3] + w2c[2, 3]  # camera z of the centres
    m = far / (far - near) * (1.0 - near / z_c.clamp_min(near))
    in_range = (z_c >= near) & (z_c <= far)
    m_ref = m[in_range].median().detach() if bool(in_range.any()) else m.new_zeros(())
    dm = (m - m_ref)[:, None]
    feats = torch.cat([colors, dm, dm * dm], dim=1)
    scales3 = torch.cat([surfels.scales, torch.ones_like(surfels.scales[:, :1])], dim=1)  # 3rd is unused in 2DGS

    render, alphas, normals_world, _, _, median, meta = rasterization_2dgs(
        surfels.means, surfels.quats, scales3, surfels.opacities, feats[None], w2c[None], K[None],
        camera.width, camera.height, near_plane=near, far_plane=far, render_mode="RGB+D", packed=False,
    )  # fmt: skip
    render, alpha = render[0], alphas[0, ..., 0]
    M1, M2, depth_sum = render[..., C], render[..., C + 1], render[..., C + 2]
    normal_world = normals_world[0]

    # means2d is a leaf on the caller's device; gsplat's densification gradient reaches it
    # through a hook.
    means2d = (meta["means2d"][0].detach() - 0.5).to(home).requires_grad_(torch.is_grad_enabled())
    densify = meta["gradient_2dgs"]
    if densify.requires_grad:

        def _copy_grad(g: torch.Tensor) -> None:
            g = g[0].to(home)
            means2d.grad = g.clone() if means2d.grad is None else means2d.grad + g

        densify.register_hook(_copy_grad)
    radii = meta["radii"][0]
    if radii.ndim == 2:  # newer gsplat: per-axis radii
        radii = radii.amax(-1)
    return RenderOutput(
        features=render[..., :C].to(home),
        alpha=alpha.to(home),
        depth_expected=(depth_sum / (alpha + depth_eps)).to(home),
        depth_median=median[0, ..., 0].to(home),
        normal_cam=(normal_world @ w2c[:3, :3].T).to(home),  # n_cam = R_wc n_world, as rows
        normal_world=normal_world.to(home),
        distortion=(alpha * M2 - M1 * M1).clamp_min(0.0).to(home),
        radii=radii.to(home, torch.int32),
        means2d=means2d,
    )
