"""Similarity transforms that bring a scene into [-1, 1]^3."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.data.hull import hull_bounds


def normalise_camera(cam: Camera, center: Tensor, scale: float) -> Camera:
    """The same camera in coordinates x' = scale * (x - center).

    Camera coordinates are scaled by ``scale`` too (projection is unchanged), so depths are in
    normalised units: w2c' = [R | scale * (R center + t)].
    """
    w2c = cam.world_to_cam.clone()
    R, t = w2c[:3, :3], w2c[:3, 3]
    w2c[:3, 3] = scale * (R @ center.to(w2c) + t)
    return replace(cam, world_to_cam=w2c)


def fit_normalisation(cameras: list[Camera], masks: list[Tensor], target: float = 0.9,
                      resolution: int = 64, where: str = "") -> tuple[Tensor, float]:
    """(center [3], scale) mapping the training masks' visual-hull box into [-target, target]^3.

    Raises DatasetError (prefixed by ``where``) if the hull is empty or unbounded (see ``hull_bounds``).
    """
    lo, hi = hull_bounds(cameras, masks, resolution=resolution, where=where)
    center = 0.5 * (lo + hi)
    half = float((0.5 * (hi - lo)).max())
    return center.to(torch.float32), target / half


def cameras_extent(cameras: list[Camera]) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera centre from their centroid."""
    c = torch.stack([cam.center.double() for cam in cameras])
    return float(1.1 * (c - c.mean(0)).norm(dim=1).max().clamp_min(1e-6))
