"""Loader check: project known 3D points through a loaded view and compare silhouettes with its mask.

A cheap, strong test of a reader's camera conventions: ground-truth surface points of the object
(in the dataset's ORIGINAL world frame) are moved into the normalised scene frame
(``world_normalised = scale * (world - center)``), projected through the view's OpenCV camera
(``Camera.project``; pixel (i, j) covers [i, i+1) x [j, j+1)) and rasterised as a point silhouette,
which is compared with the view's foreground mask. A wrong axis flip, a wrong normalisation or a
wrong time index gives a low IoU.

How the point silhouette is rasterised (so that it estimates "pixel coverage > 0.5", the quantity
``mask > 0.5`` measures):

1. each projected point marks one sub-pixel of a ``supersample``-times finer grid;
2. a morphological closing with a disc of radius ``close`` sub-pixels fills the gaps between the
   (randomly sampled) surface points; by default the radius is 1.5 x the points' own spacing (90th
   percentile of the 3D nearest-neighbour distances) projected at the median depth. Closing, unlike
   ``binary_fill_holes``, keeps real holes larger than the gap size open (cages, handles);
3. the fine grid is area-averaged back to pixels and thresholded at 0.5 (pixel coverage > 0.5).

The IoU is then taken after dilating BOTH silhouettes by ``dilate`` pixels (a symmetric boundary
tolerance: a one-pixel disagreement on an anti-aliased edge is not a calibration error). ``dilate=0``
gives the strict pixel IoU.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree
from torch import Tensor

from src.core.cameras import Camera
from src.data.base import View


def normalise_points(points: Tensor | np.ndarray, normalisation: dict | None) -> Tensor:
    """[N, 3] world points -> normalised frame ``scale * (p - center)`` (identity if ``normalisation`` is empty)."""
    p = torch.as_tensor(np.asarray(points), dtype=torch.float64).reshape(-1, 3)
    if not normalisation:
        return p
    center = torch.as_tensor(normalisation.get("center", [0.0, 0.0, 0.0]), dtype=torch.float64)
    return float(normalisation.get("scale", 1.0)) * (p - center)


def point_spacing(points: Tensor, quantile: float = 0.9, n_query: int = 4000, seed: int = 0) -> float:
    """``quantile`` of the distances from a point to its nearest neighbour (over ``n_query`` random points).

    A high quantile (not the median) so that the sparsest sampled surface (a large floor among small
    dense objects) still gets its gaps closed.
    """
    p = points.detach().cpu().double().numpy()
    if len(p) < 2:
        return 0.0
    rng = np.random.default_rng(seed)
    q = p[rng.choice(len(p), size=min(n_query, len(p)), replace=False)]
    d, _ = cKDTree(p).query(q, k=2)
    return float(np.quantile(d[:, 1], quantile))


def _disc(radius: int) -> np.ndarray:
    r = max(int(radius), 0)
    y, x = np.mgrid[-r:r + 1, -r:r + 1]
    return (x * x + y * y) <= r * r + r  # a little rounder than the strict disc for small radii


def point_silhouette(points: Tensor, camera: Camera, supersample: int = 4, close: float | None = None,
                     spacing: float | None = None, min_coverage: float = 0.5) -> np.ndarray:
    """[H, W] bool: pixels more than ``min_coverage`` covered by the object the points [N, 3] sample.

    Args:
        points: [N, 3] points in the camera's world frame.
        camera: OpenCV camera (``Camera.project``).
        supersample: sub-pixels per pixel side.
        close: closing radius in sub-pixels; None = from ``spacing`` (1.5 x the projected spacing).
        spacing: 3D point spacing (``point_spacing(points)`` if None and ``close`` is None).
        min_coverage: fraction of a pixel's sub-pixels that must be covered (0.5 matches ``mask > 0.5``;
            0 = any coverage, matching ``alpha > 0`` masks).
    """
    s = int(supersample)
    h, w = camera.height, camera.width
    uv, z = camera.project(points.to(torch.float64))
    ok = z > 1e-9
    if close is None:
        spacing = point_spacing(points) if spacing is None else spacing
        zmed = float(z[ok].median()) if ok.any() else 1.0
        close = 1.5 * spacing * max(camera.fx, camera.fy) / max(zmed, 1e-9) * s
    r = int(np.ceil(close))
    u = torch.floor(uv[:, 0] * s).long()
    v = torch.floor(uv[:, 1] * s).long()
    ok &= (u >= -r) & (u < w * s + r) & (v >= -r) & (v < h * s + r)  # points just outside close border gaps
    full = np.zeros((h * s, w * s), dtype=bool)
    if ok.any():
        u, v = u[ok].numpy(), v[ok].numpy()
        pad = r + 1
        u0, v0 = int(u.min()) - pad, int(v.min()) - pad  # work on the points' bounding box only
        crop = np.zeros((int(v.max()) - v0 + pad + 1, int(u.max()) - u0 + pad + 1), dtype=bool)
        crop[v - v0, u - u0] = True
        if r > 0:
            crop = ndimage.binary_closing(crop, structure=_disc(r)) | crop
        ya, xa = max(v0, 0), max(u0, 0)
        yb, xb = min(v0 + crop.shape[0], h * s), min(u0 + crop.shape[1], w * s)
        if yb > ya and xb > xa:
            full[ya:yb, xa:xb] = crop[ya - v0:yb - v0, xa - u0:xb - u0]
    fine = full
    return fine.reshape(h, s, w, s).mean(axis=(1, 3)) > min_coverage


def iou(a: np.ndarray, b: np.ndarray, dilate: int = 0) -> float:
    """IoU of two [H, W] bool masks after dilating both by ``dilate`` pixels (1.0 if both are empty)."""
    if dilate > 0:
        st = ndimage.generate_binary_structure(2, 2)
        a = ndimage.binary_dilation(a, st, iterations=dilate)
        b = ndimage.binary_dilation(b, st, iterations=dilate)
    union = np.logical_or(a, b).sum()
    return 1.0 if union == 0 else float(np.logical_and(a, b).sum() / union)


def silhouette_iou(points: Tensor | np.ndarray, view: View, normalisation: dict | None, dilate: int = 1,
                   supersample: int = 4, close: float | None = None, threshold: float = 0.5,
                   mask: Tensor | np.ndarray | None = None, spacing: float | None = None,
                   min_coverage: float | None = None) -> float:
    """IoU between the silhouette of ``points`` seen by ``view.camera`` and ``view.mask > threshold``.

    Args:
        points: [N, 3] points in the dataset's ORIGINAL world frame.
        view: a loaded view (normalised OpenCV camera, mask [H, W]).
        normalisation: the scene's ``{"center": [3], "scale": s}`` (world_normalised = s * (world - center)).
        dilate: symmetric boundary tolerance in pixels (both silhouettes are dilated).
        supersample, close: see :func:`point_silhouette`.
        mask: [H, W] foreground to compare with instead of ``view.mask`` (e.g. for mask-less formats).
        spacing: the points' 3D spacing in normalised units (computed if None; pass it to save time).
        min_coverage: pixel coverage the silhouette needs (default ``threshold``: a mask > 0.5 is a pixel
            more than half covered).
    """
    m = view.mask if mask is None else mask
    if m is None:
        raise ValueError(f"view {view.camera.name!r} has no mask: pass mask=...")
    m = np.asarray(m.detach().cpu().numpy() if isinstance(m, Tensor) else m) > threshold
    cam = view.camera.to("cpu", torch.float64)
    cover = threshold if min_coverage is None else min_coverage
    sil = point_silhouette(normalise_points(points, normalisation), cam, supersample, close, spacing, cover)
    if sil.shape != m.shape:
        raise ValueError(f"mask shape {m.shape} differs from the camera's image size {sil.shape}")
    return iou(sil, m, dilate)


def flip_camera_y(camera: Camera) -> Camera:
    """The camera with its y row negated (an OpenGL/OpenCV mix-up): images flip upside down."""
    w2c = camera.world_to_cam.clone()
    w2c[1] = -w2c[1]
    return replace(camera, world_to_cam=w2c)
