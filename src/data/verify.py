"""Loader check: render the ground-truth object through a loaded view and compare its silhouette with the mask.

A cheap, strong test of a reader's camera conventions: ground truth of the object in the dataset's
ORIGINAL world frame is moved into the normalised scene frame (``world_normalised = scale * (world -
center)``), projected through the view's OpenCV camera (``Camera.project``; pixel (row i, col j) covers
[j, j+1) x [i, i+1)), and its silhouette is compared with the view's foreground mask. A wrong axis flip,
a wrong normalisation or a wrong time index gives a low IoU. Two kinds of ground truth (data/README.md):

* **the render geometry itself**, a triangle mesh (``gt_mesh.npz``, :func:`load_gt_mesh`, :func:`mesh_iou`):
  rasterised exactly (:func:`mesh_coverage`: the covered fraction of ``supersample`` x ``supersample``
  sample points per pixel, any triangle, any depth). A pixel counts as foreground when its coverage
  passes the mask's own test: with a 1-pixel box filter a render's alpha IS the pixel coverage, and
  ``mask > 0.5`` on an 8-bit mask means ``round(255 alpha) >= 128``, i.e. coverage >= 127.5 / 255.
  What remains are render noise (the alpha of a 48-64 spp render scatters by ~0.03 around the
  coverage) and the 1/256 coverage steps, both only on pixels covered almost exactly half;
* **random surface points** (``gt_points.npz``, :func:`silhouette_iou`): the points' silhouette
  only approximates the surface's (see :func:`point_silhouette`): each projected point marks one
  sub-pixel of a ``supersample``-times finer grid; a morphological closing with a disc of radius
  ``close`` sub-pixels fills the gaps between the points (by default 1.5 x the points' own spacing,
  the 90th percentile of the 3D nearest-neighbour distances, projected at the median depth; closing,
  unlike ``binary_fill_holes``, keeps real holes larger than the gaps open: cages, handles); the fine
  grid is area-averaged back to pixels and thresholded (pixel coverage > 0.5). Sub-pixel parts and
  the edges of large sparsely sampled surfaces lose coverage.

Either way the IoU is taken after dilating BOTH silhouettes by ``dilate`` pixels (a symmetric boundary
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


def load_gt_mesh(path) -> tuple[Tensor, Tensor, np.ndarray | None]:
    """Read a ``gt_mesh.npz`` (written by ``tools/datagen/layouts.write_gt_mesh``; format in data/README.md).

    Returns (vertices [V, 3] or [F, V, 3] float64 in world coordinates, faces [T, 3] int64, times [F]
    float32 or None).
    """
    with np.load(path, allow_pickle=False) as z:
        q = _undelta_planes(z["vertices"])  # [3, V] or [3, V, F] uint16
        verts = z["offset"] + q.T.astype(np.float64) * z["step"]  # [V, 3] or [F, V, 3]
        faces = _undelta_planes(z["faces"]).astype(np.int64).reshape(-1, 3)
        times = z["times"] if "times" in z.files else None
    return torch.from_numpy(np.ascontiguousarray(verts)), torch.from_numpy(faces), times


def _undelta_planes(planes: np.ndarray) -> np.ndarray:
    """uint8 [2, ..., N] (low and high bytes of uint16 differences along the last axis) -> uint16 [..., N]."""
    d = planes[0].astype(np.uint16) | (planes[1].astype(np.uint16) << 8)
    return np.cumsum(d, axis=-1, dtype=np.uint16)  # wraps modulo 2^16, as the differences did


def mesh_coverage(vertices: Tensor, faces: Tensor, camera: Camera, supersample: int = 16) -> np.ndarray:
    """[H, W] float: the fraction of each pixel covered by the triangle mesh (exact rasterisation).

    Each pixel holds ``supersample``^2 sample points on a regular grid (at ((j + 0.5) / s, (i + 0.5) / s)
    inside the pixel); a sample is covered if it lies inside (or on an edge of) any triangle, whatever
    its winding or depth. Scanline rasterisation: per triangle and sample row, the covered span
    [x_left, x_right] is solved from the three edge functions and marked in a per-row difference array.

    Args:
        vertices: [V, 3] in the camera's world frame; faces: [T, 3] vertex indices.
        camera: OpenCV camera (``Camera.project``). Triangles with a vertex at or behind the camera
            plane (z <= 0) are skipped (no clipping: fine for cameras outside the object).
    """
    s = int(supersample)
    hs, ws = camera.height * s, camera.width * s
    uv, z = camera.project(vertices.to(torch.float64).reshape(-1, 3))
    f = faces.reshape(-1, 3).long().numpy()
    f = f[(z.numpy()[f] > 1e-9).all(1)]
    t = uv.numpy()[f] * s - 0.5  # [T, 3, 2] in sample units: sample (i, j) sits at x = j, y = i
    y0 = np.maximum(np.ceil(t[..., 1].min(1)), 0).astype(np.int64)
    y1 = np.minimum(np.floor(t[..., 1].max(1)), hs - 1).astype(np.int64)
    x_lo, x_hi = t[..., 0].min(1), t[..., 0].max(1)
    keep = (y1 >= y0) & (np.floor(x_hi) >= np.ceil(x_lo)) & (x_hi >= 0) & (x_lo <= ws - 1)
    t, y0, y1 = t[keep], y0[keep], y1[keep]
    a, b, c = t[:, 0], t[:, 1], t[:, 2]
    area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    neg = area2 < 0  # orient every triangle so that its edge functions are >= 0 inside
    b, c = np.where(neg[:, None], c, b), np.where(neg[:, None], b, c)
    ok = area2 != 0
    a, b, c, y0, y1 = a[ok], b[ok], c[ok], y0[ok], y1[ok]
    rows = y1 - y0 + 1
    tri = np.repeat(np.arange(len(rows)), rows)  # one entry per (triangle, sample row)
    y = (y0[tri] + np.arange(len(tri)) - np.repeat(np.cumsum(rows) - rows, rows)).astype(np.float64)
    g = np.concatenate([a, b, c], axis=1)[tri]  # [R, 6]: the triangle of each row, (x, y) of a, b, c
    left = np.full(len(tri), -np.inf)
    right = np.full(len(tri), np.inf)
    for i, j in ((0, 2), (2, 4), (4, 0)):  # edge p -> q; inside: cross(q - p, (x, y) - p) >= 0
        px, py, qx, qy = g[:, i], g[:, i + 1], g[:, j], g[:, j + 1]
        dy = qy - py  # dy < 0: x >= the edge's x at row y (a left bound), dy > 0: x <= it (a right bound);
        with np.errstate(divide="ignore", invalid="ignore"):  # a horizontal edge bounds no row of its triangle
            x_edge = px + (y - py) * (qx - px) / dy
        left = np.where(dy < 0, np.maximum(left, x_edge), left)
        right = np.where(dy > 0, np.minimum(right, x_edge), right)
    xl = np.maximum(np.ceil(left), 0)
    xr = np.minimum(np.floor(right), ws - 1)
    span = xr >= xl
    cover = np.zeros((camera.height, camera.width))
    if not span.any():
        return cover
    y, xl, xr = y[span].astype(np.int64), xl[span].astype(np.int64), xr[span].astype(np.int64)
    # work on the pixels the spans touch only
    r0, r1, c0, c1 = y.min() // s, y.max() // s + 1, xl.min() // s, xr.max() // s + 1
    h, w = (r1 - r0) * s, (c1 - c0) * s
    row = (y - r0 * s) * (w + 1) - c0 * s
    diff = (np.bincount(row + xl, minlength=h * (w + 1)) - np.bincount(row + xr + 1, minlength=h * (w + 1)))
    fine = np.cumsum(diff.reshape(h, w + 1).astype(np.int32), axis=1)[:, :w] > 0
    cover[r0:r1, c0:c1] = fine.reshape(r1 - r0, s, c1 - c0, s).sum(axis=(1, 3), dtype=np.int32) / (s * s)
    return cover


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
    m = _foreground(view, mask, threshold)
    cam = view.camera.to("cpu", torch.float64)
    cover = threshold if min_coverage is None else min_coverage
    sil = point_silhouette(normalise_points(points, normalisation), cam, supersample, close, spacing, cover)
    return _compare(sil, m, dilate)


def mesh_iou(vertices: Tensor | np.ndarray, faces: Tensor | np.ndarray, view: View, normalisation: dict | None,
             dilate: int = 1, supersample: int = 16, threshold: float = 0.5,
             mask: Tensor | np.ndarray | None = None, min_coverage: float | None = None) -> float:
    """IoU between the exact silhouette of a triangle mesh seen by ``view.camera`` and ``view.mask > threshold``.

    The silhouette holds the pixels whose coverage (:func:`mesh_coverage`) is at least ``min_coverage``,
    by default the coverage at which an 8-bit alpha passes the mask test: ``mask > threshold`` on
    ``round(255 * alpha) / 255`` means ``alpha >= (floor(255 * threshold) + 0.5) / 255`` (127.5 / 255 for
    0.5). ``threshold`` = 0 (or ``min_coverage`` = 0): any covered sample (for ``alpha > 0``-like masks).

    Args:
        vertices: [V, 3] in the dataset's ORIGINAL world frame; faces: [T, 3] vertex indices.
        view, normalisation, dilate, mask: as in :func:`silhouette_iou`.
        supersample: sample points per pixel side (see :func:`mesh_coverage`).
    """
    m = _foreground(view, mask, threshold)
    cam = view.camera.to("cpu", torch.float64)
    if min_coverage is None:
        min_coverage = (np.floor(255 * threshold) + 0.5) / 255 if threshold > 0 else 0.0
    cov = mesh_coverage(normalise_points(vertices, normalisation), torch.as_tensor(np.asarray(faces)), cam,
                        supersample)
    return _compare(cov > 0 if min_coverage <= 0 else cov >= min_coverage, m, dilate)


def _foreground(view: View, mask, threshold: float) -> np.ndarray:
    m = view.mask if mask is None else mask
    if m is None:
        raise ValueError(f"view {view.camera.name!r} has no mask: pass mask=...")
    return np.asarray(m.detach().cpu().numpy() if isinstance(m, Tensor) else m) > threshold


def _compare(sil: np.ndarray, m: np.ndarray, dilate: int) -> float:
    if sil.shape != m.shape:
        raise ValueError(f"mask shape {m.shape} differs from the camera's image size {sil.shape}")
    return iou(sil, m, dilate)


def flip_camera_y(camera: Camera) -> Camera:
    """The camera with its y row negated (an OpenGL/OpenCV mix-up): images flip upside down."""
    w2c = camera.world_to_cam.clone()
    w2c[1] = -w2c[1]
    return replace(camera, world_to_cam=w2c)
