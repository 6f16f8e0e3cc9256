"""``gcgs bench-gcf``: does the GCF loss (Eq. 4-9) built on our features have its minimum
at the true depth?

Renders a textured relief plate (and optionally the ``gcgs synth`` scenes) into real
cameras (scan24 views 23/24/33 by default), takes the reference view's ground-truth depth,
offsets it by delta (mm, camera z), and evaluates L_gcf with the default features. Writes
the curves to ``OUT/gcf_vs_depth_offset.{json,png}`` (default ``reports/priors``).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from pipeline import atomic
from pipeline.data import dtu
from pipeline.losses import gcf_loss
from pipeline.priors.features import default_features, feature_image_size
from pipeline.benchmarks.relief_scene import textured_relief_scene


def offset_curve(images: np.ndarray, K: np.ndarray, world_to_cam: np.ndarray, depth_ref_mm: np.ndarray,
                 deltas_mm: np.ndarray, ref: int = 0, feature_kwargs: dict | None = None) -> np.ndarray:
    """L_gcf of view ``ref`` against the other views for ``depth + delta``, per delta.

    ``depth_ref_mm``: (H, W) ground-truth camera z, 0 where empty (the project's convention).
    """
    H, W = depth_ref_mm.shape
    feats = [torch.from_numpy(default_features(im, **(feature_kwargs or {}))) for im in images]
    size = feature_image_size(H, W)
    sources = [(K[i], world_to_cam[i], feats[i], size) for i in range(len(images)) if i != ref]
    mask = torch.from_numpy(depth_ref_mm > 0)
    depth = torch.from_numpy(depth_ref_mm).float()
    with torch.no_grad():
        return np.array([
            float(gcf_loss(depth + float(d), K[ref], world_to_cam[ref], feats[ref], sources, valid=mask, ref_image_size=size))
            for d in deltas_mm
        ])


def relief_curve(camera_source: Path, width: int, height: int, deltas_mm: np.ndarray,
                 views=(23, 24, 33), seed: int = 0) -> tuple[np.ndarray, dict]:
    """The offset curve on the textured relief scene seen by ``camera_source``'s cameras."""
    scan = dtu.load_scene(camera_source, view_ids=list(views), resolution=(width, height), with_masks=False)
    scene = textured_relief_scene(scan.K, scan.world_to_cam, width, height, scan.norm_to_world[:3, 3], seed=seed)
    curve = offset_curve(scene.images, scene.K, scene.world_to_cam, scene.depth_mm[0], deltas_mm)
    info = {"scene": "textured relief plate (300 mm, 15 mm bumps, per-view exposure change)",
            "cameras": f"{camera_source} views {list(views)}", "width": width, "height": height,
            "reference_view": views[0], "seed": seed}
    return curve, info


def synth_curve(name: str, camera_source: Path, width: int, height: int, deltas_mm: np.ndarray,
                views=(23, 24, 33), seed: int = 0) -> tuple[np.ndarray, dict]:
    """The offset curve on a ``gcgs synth`` scene rendered into the given views (every
    pixel where the scene's geometry, object or ground, is hit)."""
    from pipeline.synth import Renderer, build_scene

    scan = dtu.load_scene(camera_source, view_ids=list(views), resolution=(width, height), with_masks=False)
    renderer = Renderer(build_scene(name, seed, dtu.load_cameras(camera_source)))
    hits = [renderer.cast(K, T, width, height) for K, T in zip(scan.K, scan.world_to_cam)]
    images = np.stack([renderer.shade(h) for h in hits]).astype(np.float32)
    curve = offset_curve(images, scan.K, scan.world_to_cam, hits[0]["depth"], deltas_mm)
    info = {"scene": f"{name} (pipeline.synth, seed {seed})", "cameras": f"{camera_source} views {list(views)}",
            "width": width, "height": height, "reference_view": views[0]}
    return curve, info


def init_depth_curve(scene_dir: Path, init_dir: Path, deltas_mm: np.ndarray) -> tuple[np.ndarray, dict]:
    """The offset curve on a real scene, around the init stage's depth of its first view.

    Not ground truth: that depth was itself found by maximising NCC, so a minimum at 0
    mostly shows that the features agree across the real views' lighting.
    """
    from pipeline.init.io import depth_path, read_depth

    scene = dtu.load_scene(scene_dir, view_ids=None)
    d = read_depth(depth_path(init_dir, scene.view_ids[0]))
    depth = np.where(d.valid, d.depth_mm, 0.0)
    curve = offset_curve(scene.images, scene.K, scene.world_to_cam, depth, deltas_mm)
    info = {"scene": f"{scene_dir} (real images)", "reference_depth": f"{init_dir} (init stage, valid pixels)",
            "width": scene.width, "height": scene.height, "reference_view": scene.view_ids[0],
            "valid_fraction": round(float(d.valid.mean()), 4)}
    return curve, info


def summarise(deltas: np.ndarray, curve: np.ndarray, info: dict) -> dict:
    i = int(np.argmin(curve))
    return {**info, "loss": [round(float(v), 6) for v in curve], "argmin_delta_mm": float(deltas[i]),
            "loss_at_0": float(curve[np.argmin(np.abs(deltas))]), "loss_at_minus10": float(curve[0]),
            "loss_at_plus10": float(curve[-1])}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cameras", default="data/raw/dtu/scan24")
    p.add_argument("--width", type=int, default=800)
    p.add_argument("--height", type=int, default=600)
    p.add_argument("--synth", nargs="*", default=[], help="also: these gcgs synth scenes")
    p.add_argument("--scene", default=None, help="also: a prepared real scene ...")
    p.add_argument("--init-dir", default=None, help="... and its init output (reference depth)")
    p.add_argument("--delta-step", type=float, default=0.5, help="offset step, mm (offsets -10 .. +10 mm)")
    p.add_argument("--out", default="reports/priors")


def run(args: argparse.Namespace) -> int:
    if not args.delta_step > 0:
        raise ValueError(f"--delta-step must be > 0 mm, got {args.delta_step}")
    atomic.check_output_file(Path(args.out) / "gcf_vs_depth_offset.json")  # refused now, not after the curves
    deltas = np.round(np.arange(-10.0, 10.0 + 1e-9, args.delta_step), 6)
    t0 = time.perf_counter()
    cams = Path(args.cameras)
    curves = {"relief plate": summarise(deltas, *relief_curve(cams, args.width, args.height, deltas))}
    for name in args.synth:
        curves[name] = summarise(deltas, *synth_curve(name, cams, args.width, args.height, deltas))
    if args.scene and args.init_dir:
        curves["scan24 real"] = summarise(deltas, *init_depth_curve(Path(args.scene), Path(args.init_dir), deltas))
    result = {"features": "default (5x5 normalised patches at dilations 1 and 2, 1/2 resolution)",
              "delta_mm": deltas.tolist(), "curves": curves, "seconds": round(time.perf_counter() - t0, 1)}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    atomic.write_text(out / "gcf_vs_depth_offset.json", json.dumps(result, indent=1) + "\n")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=120)
    for k, (name, c) in enumerate(curves.items()):
        what = "real images, init MVS depth" if name == "scan24 real" else "rendered, true depth"
        ax.plot(deltas, c["loss"], "-o", ms=2.0, color=f"C{k}",
                label=f"{name}: {what} (argmin {c['argmin_delta_mm']:+.1f} mm)")
    ax.axvline(0.0, color="0.6", lw=0.8, ls="--")
    ax.set_xlabel("depth offset delta (mm, camera z of the reference view)")
    ax.set_ylabel("L_gcf (Eq. 4-9)")
    ax.set_title(f"GCF loss vs depth offset, default features, {args.width}x{args.height}, views 23 | 24, 33", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "gcf_vs_depth_offset.png")
    for name, c in curves.items():
        print(f"{name}: argmin delta = {c['argmin_delta_mm']:+.2f} mm")
    print(f"wrote {out}/gcf_vs_depth_offset.{{json,png}}")
    return 0
