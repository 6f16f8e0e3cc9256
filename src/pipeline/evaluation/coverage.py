"""Accuracy on the surface a reference mesh also has, and on the surface only this mesh adds.

DTU accuracy is a mean over a mesh's own surface, so two meshes of different extent are
scored on different surfaces: one that covers more of the object (better completeness) is
charged for the harder surface it adds. Splitting a mesh by a reference (the MVS+TSDF
baseline) separates the two: on the ``shared`` part (triangles whose centroid lies within
``within_mm`` of the reference) the two meshes answer the same question; the ``added`` part
is what this mesh has and the reference does not. World mm.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from pipeline.config.evaluate import EvaluateConfig
from pipeline.evaluation.dtu_eval import CullView, evaluate_mesh
from pipeline.evaluation.gt import GroundTruth
from pipeline.evaluation.sampling import check_mesh
from pipeline.raycast import MeshCaster

PARTS = ("shared", "added")


def split_by_reference(vertices_mm: np.ndarray, triangles: np.ndarray, ref_vertices_mm: np.ndarray,
                       ref_triangles: np.ndarray, within_mm: float) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The mesh's triangles whose centroid is within ``within_mm`` of the reference mesh
    (``shared``) and the others (``added``), each as ``(vertices, triangles)`` with only the
    vertices its triangles use."""
    if not (within_mm > 0 and math.isfinite(within_mm)):
        raise ValueError(f"split_by_reference: within_mm must be a positive finite distance, got {within_mm}")
    V, F = check_mesh(vertices_mm, triangles)
    ref_V, ref_F = check_mesh(ref_vertices_mm, ref_triangles, name="reference mesh")
    near = MeshCaster(ref_V, ref_F).distance(V[F].mean(axis=1)) < within_mm
    return {"shared": _triangle_submesh(V, F[near]), "added": _triangle_submesh(V, F[~near])}


def _triangle_submesh(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, index = np.unique(F.ravel(), return_inverse=True)
    return V[used], index.reshape(F.shape)


def accuracy_by_reference(vertices_mm: np.ndarray, triangles: np.ndarray, ref_vertices_mm: np.ndarray,
                          ref_triangles: np.ndarray, gt: GroundTruth, cfg: EvaluateConfig,
                          views: list[CullView] | None = None, seed: int = 0, within_mm: float = 1.0,
                          log: Callable[[str], None] | None = print) -> dict:
    """DTU accuracy of each part of :func:`split_by_reference`, scored as a whole mesh is
    (culled, sampled, downsampled, the same ``cfg``): per part, ``fraction`` of the accuracy
    points (those within ``cfg.max_dist_mm`` of the GT) it holds and ``accuracy_mm`` (NaN for an
    empty part). The parts' accuracies weighted by ``fraction`` give back the whole mesh's
    accuracy up to the downsampling near the cut."""
    parts = split_by_reference(vertices_mm, triangles, ref_vertices_mm, ref_triangles, within_mm)
    scored = {}
    for name in PARTS:
        V, F = parts[name]
        if not len(F):
            scored[name] = (math.nan, 0)
            continue
        m = evaluate_mesh(V, F, gt, cfg, views=views, seed=seed, log=None, name=f"{name} part")
        scored[name] = (m["accuracy_mm"], m["counts"]["accuracy_used"])
    total = sum(n for _, n in scored.values())
    out = {"within_mm": within_mm}
    for name in PARTS:
        acc, n = scored[name]
        out[name] = {"fraction": n / total if total else math.nan, "accuracy_mm": acc}
    if log:
        log("[evaluate] accuracy by reference coverage: " + ", ".join(
            f"{p}: {100 * out[p]['fraction']:.1f}% at {out[p]['accuracy_mm']:.3f} mm" for p in PARTS))
    return out
