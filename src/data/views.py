"""Deterministic sparse-view selection (the SplatFields protocol).

The paper's rule: K-means with K = n_views clusters on the training camera centres (fixed seed),
then for each cluster centre the nearest camera; the chosen indices are sorted. The reference code
used scikit-learn's KMeans(random_state=0); we implement Lloyd's algorithm with k-means++ seeding and
10 restarts in NumPy (seed 0), so the chosen ids may differ from the authors' on the same data.
"""

from __future__ import annotations

import numpy as np

from src.data.base import DatasetError


def kmeans(points: np.ndarray, k: int, seed: int = 0, n_init: int = 10, iters: int = 300) -> np.ndarray:
    """Cluster centres [k, D] of ``points`` [N, D] (best of ``n_init`` k-means++ runs by inertia)."""
    rng = np.random.default_rng(seed)
    best, best_inertia = None, np.inf
    for _ in range(n_init):
        centres = [points[rng.integers(len(points))]]
        for _ in range(1, k):
            d2 = np.min(((points[:, None] - np.asarray(centres)[None]) ** 2).sum(-1), axis=1)
            p = d2 / d2.sum() if d2.sum() > 0 else np.full(len(points), 1.0 / len(points))
            centres.append(points[rng.choice(len(points), p=p)])
        c = np.asarray(centres, dtype=np.float64)
        for _ in range(iters):
            lab = np.argmin(((points[:, None] - c[None]) ** 2).sum(-1), axis=1)
            new = np.array([points[lab == j].mean(0) if np.any(lab == j) else c[j] for j in range(k)])
            if np.allclose(new, c):
                break
            c = new
        inertia = np.min(((points[:, None] - c[None]) ** 2).sum(-1), axis=1).sum()
        if inertia < best_inertia:
            best, best_inertia = c, inertia
    return best


def select_views(centres: np.ndarray, n_views: int | None, seed: int = 0) -> list[int]:
    """Indices of ``n_views`` training cameras spread over the camera centres [N, 3].

    ``None`` (or n_views == N) keeps every view. Raises DatasetError (a ValueError) for n_views outside [1, N].
    """
    n = len(centres)
    if n_views is None or n_views == n:
        return list(range(n))
    if not 1 <= n_views <= n:
        raise DatasetError(f"dataset.n_views={n_views} must be between 1 and the {n} available training views")
    c = kmeans(np.asarray(centres, dtype=np.float64), n_views, seed=seed)
    chosen: list[int] = []
    for centre in c:
        d = ((centres - centre) ** 2).sum(-1)
        for idx in np.argsort(d):  # nearest camera not already taken
            if int(idx) not in chosen:
                chosen.append(int(idx))
                break
    return sorted(chosen)
