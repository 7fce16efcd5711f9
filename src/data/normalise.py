"""Similarity transforms that normalise a scene: the training masks' visual hull into [-0.9, 0.9]^3 or,
without masks, the training camera centres into the unit ball (3DGS's camera sphere)."""

from __future__ import annotations

from dataclasses import replace

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.data.base import DatasetError
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


def camera_sphere(cameras: list[Camera]) -> tuple[Tensor, float]:
    """(centre [3] float64, radius) of the camera centres, 3DGS's convention: the centre is their mean,
    the radius 1.1 x the largest distance of a camera centre from it."""
    c = torch.stack([cam.center.double() for cam in cameras])  # [N, 3]
    centre = c.mean(0)
    return centre, float(1.1 * (c - centre).norm(dim=1).max())


def cameras_extent(cameras: list[Camera]) -> float:
    """3DGS's scene extent: 1.1 x the largest distance of a camera centre from their centroid."""
    return max(camera_sphere(cameras)[1], 1.1e-6)


def fit_camera_normalisation(cameras: list[Camera], where: str = "") -> tuple[Tensor, float]:
    """(center [3], scale) for scenes without masks: x' = scale * (x - center) with the camera sphere's
    centre and scale = 1 / its radius (:func:`camera_sphere`), so every camera centre lies within
    1 / 1.1 of the origin and :func:`cameras_extent` of the normalised cameras is 1.

    Raises DatasetError (prefixed by ``where``) if the cameras share one centre (nothing to scale by).
    """
    centre, radius = camera_sphere(cameras)
    if not radius > 1e-9 * max(1.0, float(centre.abs().max())):
        raise DatasetError(f"{where}: the {len(cameras)} training camera(s) share one centre; normalising from "
                           "camera centres needs at least two distinct ones (more views, or dataset.normalise=false)")
    return centre.to(torch.float32), 1.0 / radius
