"""Differentiable rasterizer of 2D Gaussian surfels (2DGS), one interface, four backends.

    out = rasterize(Surfels(means, quats, scales, opacities, features), Camera(K, world_to_cam, W, H), "auto")

* ``cpu``: hand-written numba forward/backward kernels, multithreaded over 16x16 tiles.
* ``simd``: ``cpu`` with its set-up and compositing kernels in C++ (float32 vector lanes),
  built on first use by the system's compiler; ``auto`` picks it wherever it builds.
* ``reference``: dense pure PyTorch with autograd; the oracle for tests.
* ``cuda``: gsplat's ``rasterization_2dgs`` (needs CUDA and gsplat); it composites
  surfel-centre depths, see ``docs/rasterizer.md``.

Maths and conventions: ``docs/rasterizer.md``.
"""
from __future__ import annotations

import sys

import torch

from pipeline.errors import ConfigError
from pipeline.rasterizer.project import colors_of, project
from pipeline.rasterizer.types import Camera, RenderOutput, Surfels

BACKENDS = ("cpu", "simd", "reference", "cuda")

__all__ = ["BACKENDS", "Camera", "RenderOutput", "Surfels", "rasterize", "resolve_backend"]


def resolve_backend(name: str) -> str:
    """A backend name of params ``optimize.backend`` as one of :data:`BACKENDS`.

    ``auto`` is ``simd`` where its kernels build, else ``cpu`` (one line on stderr says why),
    also where a GPU is: ``cuda`` (gsplat) composites surfel-centre depth, a different method
    that measured worse (docs/rasterizer.md, "The cuda backend, run"), so it runs only when
    named. Naming ``simd`` where its kernels do not build is an error that says why."""
    if name == "auto":
        return _cpu_kernels()
    if name == "simd":
        from pipeline.rasterizer import simd

        ok, why = simd.available()
        if not ok:
            raise ConfigError(f"optimize.backend is simd but its kernels do not build here: {why.splitlines()[0]} (use auto or cpu)")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("optimize.backend is cuda but no CUDA device is available (use auto or cpu)")
    return name


_fallback_said: list[str] = []


def _cpu_kernels() -> str:
    """``simd`` where its kernels build, else ``cpu``, saying why once per process."""
    from pipeline.rasterizer import simd

    ok, why = simd.available()
    if ok:
        return "simd"
    if not _fallback_said:
        _fallback_said.append(why)
        print(f"gcgs: warning: the simd rasterizer kernels do not build here ({why.splitlines()[0]}); "
              "using the numba cpu kernels (slower, same results to float32 rounding)", file=sys.stderr)
    return "cpu"


def rasterize(
    surfels: Surfels,
    camera: Camera,
    backend: str = "cpu",
    *,
    depth_eps: float = 1e-6,
    reference_block: int | None = None,
) -> RenderOutput:
    """Render ``surfels`` seen by ``camera``; every map is differentiable w.r.t. every
    surfel parameter (see ``RenderOutput`` for frames and units).

    Args:
        backend: one of :data:`BACKENDS`, or ``auto``: ``cuda`` for CUDA tensors, else
            ``simd`` where its kernels build and take these surfels (float32, at most 8
            feature channels), else ``cpu``.
        depth_eps: the ``eps`` of ``depth_expected = sum w z / (sum w + eps)``.
        reference_block: ``reference`` backend only: ``None`` evaluates every pixel
            against every surfel; ``B`` works in ``B x B`` pixel blocks against the
            surfels whose support box touches the block (same result, less memory).
    """
    if backend == "auto":
        backend = _auto_for(surfels)
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of auto, {', '.join(BACKENDS)}")
    if not (depth_eps >= 0 and depth_eps < float("inf")):
        raise ValueError(f"depth_eps must be finite and >= 0, got {depth_eps}")
    if reference_block is not None and (backend != "reference" or reference_block < 1):
        raise ValueError("reference_block is a positive block size for the reference backend only")
    if backend == "cuda":
        from pipeline.rasterizer import cuda

        return cuda.rasterize(surfels, camera, depth_eps=depth_eps)
    if surfels.means.device.type != "cpu":
        raise ValueError(f"the {backend} backend needs CPU tensors, got {surfels.means.device}")

    if backend in ("cpu", "simd"):
        from pipeline.rasterizer import cpu, simd

        render = simd.render if backend == "simd" else cpu.render
        maps, radii, means2d, _ = render(
            surfels.means, surfels.quats, surfels.scales, surfels.opacities, colors_of(surfels, camera), camera, depth_eps
        )
        return RenderOutput(*maps, radii=radii, means2d=means2d)

    from pipeline.rasterizer import reference

    proj = project(surfels, camera, track_means2d=torch.is_grad_enabled())
    features, alpha, depth_sum, normal_cam, median, distortion = reference.render(proj, camera, block=reference_block)
    R_wc = camera.world_to_cam[:3, :3].to(normal_cam.dtype)
    return RenderOutput(
        features=features,
        alpha=alpha,
        depth_expected=depth_sum / (alpha + depth_eps),
        depth_median=median,
        normal_cam=normal_cam,
        normal_world=normal_cam @ R_wc,  # n_world = R_wc^T n_cam, as rows
        distortion=distortion,
        radii=proj.radii,
        means2d=proj.means2d,
    )


def _auto_for(surfels: Surfels) -> str:
    """``rasterize``'s ``auto``: per call, since the simd kernels take float32 only."""
    if surfels.means.device.type == "cuda":
        return "cuda"
    if _cpu_kernels() == "cpu":
        return "cpu"
    from pipeline.rasterizer import simd

    # colors_of keeps the features' dtype and last dimension (SH evaluates to the same channels)
    channels = surfels.features.new_empty((0, surfels.features.shape[-1]))
    return "cpu" if simd.unsuited(surfels.means, channels) else "simd"
