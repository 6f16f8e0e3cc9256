"""The ``sfm`` backend: SIFT features matched between the input views and triangulated
with the known cameras (the sparse initialisation of the 2DGS baseline).

Per pair of views: Lowe's ratio test, then the epipolar constraint of the *known*
cameras (distance to the epipolar line, both ways). Matches are chained into multi-view
tracks (union-find; a track that would hold two features of one view is dropped),
triangulated by linear DLT over all its views, and kept when every view sees it in
front of the camera within ``reproj_px`` of its feature, the widest triangulation angle
is at least ``min_angle_deg`` and it lies in the scene sphere.

Confidence per point = exp(-mean reprojection error / reproj_px) * (views - 1) / (N - 1).
"""
from __future__ import annotations

import cv2
import numpy as np

from pipeline import geometry
from pipeline.config.init import InitConfig
from pipeline.data.scene import Scene
from pipeline.init.fusion import estimate_normals
from pipeline.init.io import InitResult, PointCloud


def fundamental(K_i, T_i, K_j, T_j) -> np.ndarray:
    """F with ``x_j^T F x_i = 0`` for pixels of the same point (known cameras)."""
    T = T_j @ geometry.rigid_inverse(T_i)
    R, t = T[:3, :3], T[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K_j).T @ tx @ R @ np.linalg.inv(K_i)


def epipolar_distance(F: np.ndarray, x_i: np.ndarray, x_j: np.ndarray) -> np.ndarray:
    """Larger of the two point-to-epipolar-line distances (pixels), ``(M, 2)`` inputs."""
    hi = np.c_[x_i, np.ones(len(x_i))]
    hj = np.c_[x_j, np.ones(len(x_j))]
    l_j = hi @ F.T  # lines in view j
    l_i = hj @ F  # lines in view i
    num = np.abs(np.einsum("ij,ij->i", hj, l_j))
    return np.maximum(num / np.hypot(l_j[:, 0], l_j[:, 1]), num / np.hypot(l_i[:, 0], l_i[:, 1]))


def triangulate_tracks(P: np.ndarray, obs: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Linear DLT for many tracks at once.

    Args:
        P: ``(N, 3, 4)`` projections (world mm -> pixels).
        obs: ``(T, N, 2)`` pixel of each track in each view; ``seen``: ``(T, N)`` bool.
    Returns ``(T, 3)`` world points (mm).
    """
    rows_x = obs[:, :, 0:1] * P[None, :, 2, :] - P[None, :, 0, :]  # (T, N, 4)
    rows_y = obs[:, :, 1:2] * P[None, :, 2, :] - P[None, :, 1, :]
    A = np.concatenate([rows_x, rows_y], 1) * np.concatenate([seen, seen], 1)[..., None]
    # Row scaling does not move the DLT solution but keeps the SVD well conditioned.
    A /= np.maximum(np.linalg.norm(A, axis=2, keepdims=True), 1e-12)
    _, _, vt = np.linalg.svd(A)
    X = vt[:, -1]
    return X[:, :3] / X[:, 3:4]


class _UnionFind:
    def __init__(self, n: int) -> None:
        self.parent = np.arange(n)

    def find(self, a: int) -> int:
        root = a
        while self.parent[root] != root:
            root = self.parent[root]
        while self.parent[a] != root:
            self.parent[a], a = root, self.parent[a]
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)


def run(scene: Scene, cfg: InitConfig) -> InitResult:
    p = cfg.sfm
    N = scene.num_views
    sift = cv2.SIFT_create(nfeatures=p.max_features)
    kps, descs = [], []
    for i in range(N):
        grey = cv2.cvtColor((scene.images[i] * 255).round().astype(np.uint8), cv2.COLOR_RGB2GRAY)
        mask = None if scene.masks is None else scene.masks[i].astype(np.uint8) * 255
        k, d = sift.detectAndCompute(grey, mask)
        kps.append(np.array([kp.pt for kp in k], np.float64).reshape(-1, 2))
        descs.append(d if d is not None else np.zeros((0, 128), np.float32))
    offsets = np.cumsum([0] + [len(k) for k in kps])
    uf = _UnionFind(int(offsets[-1]))
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    pair_matches = {}
    for i in range(N):
        for j in range(i + 1, N):
            if len(descs[i]) < 2 or len(descs[j]) < 2:
                continue
            knn = matcher.knnMatch(descs[i], descs[j], k=2)
            m = np.array([(a.queryIdx, a.trainIdx) for a, b in (x for x in knn if len(x) == 2)
                          if a.distance < p.ratio * b.distance], np.int64).reshape(-1, 2)
            F = fundamental(scene.K[i], scene.world_to_cam[i], scene.K[j], scene.world_to_cam[j])
            m = m[epipolar_distance(F, kps[i][m[:, 0]], kps[j][m[:, 1]]) < p.epipolar_px]
            pair_matches[(i, j)] = len(m)
            for a, b in m:
                uf.union(offsets[i] + a, offsets[j] + b)

    # Tracks: components with >= 2 features and at most one feature per view.
    view_of = np.repeat(np.arange(N), np.diff(offsets))
    roots = np.array([uf.find(a) for a in range(int(offsets[-1]))], np.int64)
    uniq, track_id, sizes = np.unique(roots, return_inverse=True, return_counts=True)
    T = len(uniq)
    obs = np.zeros((T, N, 2))
    seen = np.zeros((T, N), bool)
    dup = np.zeros(T, bool)
    for f in np.nonzero(sizes[track_id] >= 2)[0]:
        t, v = track_id[f], view_of[f]
        dup[t] |= seen[t, v]
        seen[t, v] = True
        obs[t, v] = kps[v][f - offsets[v]]
    keep = (seen.sum(1) >= 2) & ~dup
    obs, seen = obs[keep], seen[keep]
    info = {"features": [len(k) for k in kps], "pair_matches": {f"{i}-{j}": n for (i, j), n in pair_matches.items()},
            "tracks": int(len(obs))}
    if len(obs) == 0:
        return InitResult(PointCloud(np.zeros((0, 3)), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                                     np.zeros(0, np.float32)), None, info)

    P = scene.projections_world()[:, :3, :]
    X = triangulate_tracks(P, obs, seen)
    err = np.zeros(len(X))
    ok = np.ones(len(X), bool)
    centres = scene.camera_centers_world_mm()
    rays = []
    for v in range(N):
        px, z = geometry.project(scene.K[v], scene.world_to_cam[v], X)
        e = np.linalg.norm(px - obs[:, v], axis=1)
        ok &= ~seen[:, v] | ((z > 0) & (e < p.reproj_px))
        err += np.where(seen[:, v], np.nan_to_num(e, nan=1e9), 0.0)
        r = X - centres[v]
        rays.append(r / np.linalg.norm(r, axis=1, keepdims=True))
    max_angle = np.zeros(len(X))
    for a in range(N):
        for b in range(a + 1, N):
            both = seen[:, a] & seen[:, b]
            ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", rays[a], rays[b]), -1, 1)))
            max_angle = np.where(both, np.maximum(max_angle, ang), max_angle)
    in_sphere = np.linalg.norm(X - scene.norm_to_world[:3, 3], axis=1) <= cfg.mvs.sphere_margin * scene.norm_scale_mm
    ok &= (max_angle >= p.min_angle_deg) & in_sphere
    X, obs, seen, err = X[ok], obs[ok], seen[ok], err[ok]
    nviews = seen.sum(1)
    conf = np.exp(-(err / nviews) / p.reproj_px) * (nviews - 1) / max(N - 1, 1)

    colors = np.zeros((len(X), 3))
    toward = np.zeros((len(X), 3))
    for v in range(N):
        ij = np.round(obs[:, v]).astype(np.int64)
        ij[:, 0] = ij[:, 0].clip(0, scene.width - 1)
        ij[:, 1] = ij[:, 1].clip(0, scene.height - 1)
        colors += seen[:, v, None] * scene.images[v, ij[:, 1], ij[:, 0]]
        d = centres[v] - X
        toward += seen[:, v, None] * d / np.linalg.norm(d, axis=1, keepdims=True)
    colors /= nviews[:, None]
    normals = estimate_normals(X, toward, cfg.normal_knn)
    info.update(points=int(len(X)), mean_reproj_px=float((err / nviews).mean()) if len(X) else None,
                track_lengths={int(n): int((nviews == n).sum()) for n in np.unique(nviews)})
    cloud = PointCloud(X, colors.astype(np.float32), normals, conf.astype(np.float32))
    return InitResult(cloud, None, info)
