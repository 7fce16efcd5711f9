"""Nearest-neighbour scales for splat initialisation."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor


def knn_base_scale(points: Tensor, k: int = 3) -> Tensor:
    """[N] sqrt of the mean squared distance to the ``k`` nearest other points (3DGS ``distCUDA2``).

    Clamped below at 1e-7 so its logarithm is finite (also for duplicate points).
    """
    p = points.detach().cpu().double().numpy()
    if len(p) < 2:
        return torch.full((len(p),), 0.01, dtype=points.dtype, device=points.device)
    kk = min(k + 1, len(p))
    d, _ = cKDTree(p).query(p, k=kk)
    d = np.asarray(d)[:, 1:]
    s = np.sqrt((d**2).mean(axis=1))
    return torch.from_numpy(np.maximum(s, 1e-7)).to(points)
