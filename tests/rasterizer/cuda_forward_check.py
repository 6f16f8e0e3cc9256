"""Where the cuda backend's forward differs from the cpu backend's (docs/rasterizer.md,
"The cuda backend, run"): the test scene of ``tests/rasterizer/test_rasterizer_cuda.py``
map by map, then each surfel alone, with and without the camera's skew, and gsplat's
CUDA kernel against gsplat's own pure-torch rasteriser on the same projected surfels.

    python tests/rasterizer/cuda_forward_check.py OUT.json

Needs CUDA and gsplat; run from the repository root with ``src`` importable. It lives
beside the test whose scene it takes (``raster_helpers``), not in scripts/.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from raster_helpers import random_camera, random_surfels  # noqa: E402

from pipeline.rasterizer import Camera, Surfels, rasterize  # noqa: E402


def _rel(cpu: torch.Tensor, cuda: torch.Tensor) -> dict:
    d = (cpu - cuda).abs()
    top = cuda.abs().max().clamp_min(1e-12)
    if d.ndim == 3:
        d = d.amax(-1)
    flat = int(d.argmax())
    return {"max_rel": float(d.max() / top), "mean_rel": float(d.mean() / top),
            "share_above_1pct": float((d > 0.01 * top).float().mean()),
            "worst_pixel_row_col": [flat // d.shape[1], flat % d.shape[1]]}


def _subset(s: Surfels, idx) -> Surfels:
    return Surfels(s.means[idx], s.quats[idx], s.scales[idx], s.opacities[idx], s.features[idx], s.sh_degree)


def _without_skew(cam: Camera) -> Camera:
    K = cam.K.clone()
    K[0, 1] = 0.0
    return Camera(K, cam.world_to_cam, cam.width, cam.height, cam.near, cam.far)


def compare_maps(s: Surfels, cam: Camera) -> dict:
    a, b = rasterize(s, cam, "cpu"), rasterize(s, cam, "cuda")
    out = {k: _rel(getattr(a, k), getattr(b, k).cpu()) for k in ("features", "alpha", "normal_cam")}
    hit = (a.alpha > 0.5) & (b.alpha.cpu() > 0.5)
    for k in ("depth_expected", "depth_median"):
        x, y = getattr(a, k)[hit], getattr(b, k).cpu()[hit]
        out[k] = {"mean_rel": float((x - y).abs().mean() / x.mean()), "max_rel": float((x - y).abs().max() / x.mean()),
                  "signed_mean_rel": float((y - x).mean() / x.mean()), "pixels": int(hit.sum())}
    return out


def single_surfels(s: Surfels, cam: Camera, count: int) -> dict:
    """Each surfel rendered alone: max |alpha_cpu - alpha_cuda| and where."""
    rows = []
    for i in range(min(count, s.means.shape[0])):
        one = _subset(s, [i])
        a, b = rasterize(one, cam, "cpu").alpha, rasterize(one, cam, "cuda").alpha.cpu()
        d = (a - b).abs()
        flat = int(d.argmax())
        z = float(one.means[0] @ cam.world_to_cam[2, :3].float() + cam.world_to_cam[2, 3])
        rows.append({"i": i, "max_abs": float(d.max()), "at_row_col": [flat // cam.width, flat % cam.width],
                     "alpha_cpu_there": float(a.view(-1)[flat]), "alpha_cuda_there": float(b.view(-1)[flat]),
                     "opacity": float(one.opacities[0]), "depth": z,
                     "covered_cpu": int((a > 1e-4).sum()), "covered_cuda": int((b > 1e-4).sum())})
    worst = sorted(rows, key=lambda r: -r["max_abs"])
    q = torch.tensor([r["max_abs"] for r in rows])
    return {"surfels": len(rows), "max_abs_quantiles_50_90_99_100": [float(q.quantile(p)) for p in (0.5, 0.9, 0.99, 1.0)],
            "share_above_1e-2": float((q > 1e-2).float().mean()), "worst": worst[:8]}


def gsplat_cuda_vs_its_torch(s: Surfels, cam: Camera) -> dict:
    """gsplat's CUDA rasteriser against its pure-torch one, both fed gsplat's projection."""
    from gsplat.cuda._torch_impl_2dgs import _rasterize_to_pixels_2dgs
    from gsplat.cuda._wrapper import fully_fused_projection_2dgs, isect_offset_encode, isect_tiles, \
        rasterize_to_pixels_2dgs

    dev = "cuda"
    K = cam.K.clone()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    K, w2c = K.to(dev, torch.float32)[None], cam.world_to_cam.to(dev, torch.float32)[None]
    scales3 = torch.cat([s.scales, torch.ones_like(s.scales[:, :1])], 1).to(dev)
    radii, means2d, depths, ray_transforms, normals = fully_fused_projection_2dgs(
        s.means.to(dev), torch.nn.functional.normalize(s.quats.to(dev), dim=-1), scales3, w2c, K, cam.width,
        cam.height, near_plane=cam.near, far_plane=cam.far)  # fmt: skip
    colors = torch.cat([s.features.to(dev)[None], depths[..., None]], -1)
    opac = s.opacities.to(dev)[None]
    tile = 16
    tw, th = math.ceil(cam.width / tile), math.ceil(cam.height / tile)
    _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile, tw, th)
    offsets = isect_offset_encode(isect_ids, 1, tw, th).reshape(1, th, tw)
    densify = torch.zeros_like(means2d)
    cuda_out = rasterize_to_pixels_2dgs(means2d, ray_transforms, colors, opac, normals, densify, cam.width,
                                        cam.height, tile, offsets, flatten_ids)
    torch_out = _rasterize_to_pixels_2dgs(means2d, ray_transforms, colors, normals, opac, cam.width, cam.height,
                                          tile, offsets, flatten_ids)
    return {"colours": _rel(torch_out[0][0, ..., :3].cpu(), cuda_out[0][0, ..., :3].cpu()),
            "alpha": _rel(torch_out[1][0, ..., 0].cpu(), cuda_out[1][0, ..., 0].cpu())}


@torch.no_grad()
def main() -> None:
    out_path = Path(sys.argv[1])
    result: dict = {"device": torch.cuda.get_device_name(0), "torch": torch.__version__}
    try:
        import gsplat

        result["gsplat"] = getattr(gsplat, "__version__", "?")
    except ImportError as exc:
        raise SystemExit(f"gsplat is not importable: {exc}")
    cam = random_camera(64, 48, 11)
    s = random_surfels(500, cam, seed=11, dtype=torch.float32, opacity=(0.05, 0.9))
    for name, c in (("skewed_camera", cam), ("no_skew", _without_skew(cam))):
        entry = result.setdefault(name, {})
        for part, fn in (("maps", lambda: compare_maps(s, c)), ("single_surfels", lambda: single_surfels(s, c, 500)),
                         ("gsplat_cuda_vs_gsplat_torch", lambda: gsplat_cuda_vs_its_torch(s, c))):
            try:
                entry[part] = fn()
            except Exception as exc:  # a diagnostic: record and go on
                entry[part] = {"error": repr(exc)}
            out_path.write_text(json.dumps(result, indent=1) + "\n")
            print(name, part, json.dumps(entry[part])[:600], flush=True)


if __name__ == "__main__":
    main()
