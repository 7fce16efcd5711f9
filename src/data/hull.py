"""Visual hulls from calibrated masks: scene normalisation and splat initialisation.

A point belongs to the visual hull if it projects inside every given view's image onto a mask
value above ``threshold`` (nearest pixel). Conventions: OpenCV cameras, pixel (i, j) covers
[i, i+1) x [j, j+1).
"""

from __future__ import annotations

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.data.base import DatasetError


def inside_hull(points: Tensor, cameras: list[Camera], masks: list[Tensor], threshold: float = 0.0,
                chunk: int = 1 << 18) -> Tensor:
    """[N] bool: does each point [N, 3] land on mask > threshold in every view (and inside the image)?"""
    keep = torch.ones(points.shape[0], dtype=torch.bool)
    for start in range(0, points.shape[0], chunk):
        p = points[start:start + chunk]
        k = torch.ones(p.shape[0], dtype=torch.bool)
        for cam, mask in zip(cameras, masks, strict=True):
            uv, z = cam.project(p.to(cam.world_to_cam.dtype))
            u = torch.floor(uv[:, 0]).long()
            v = torch.floor(uv[:, 1]).long()
            ok = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
            val = torch.zeros(p.shape[0], dtype=mask.dtype)
            val[ok] = mask.cpu()[v[ok], u[ok]]
            k &= ok & (val > threshold)
        keep[start:start + chunk] = k
    return keep


def axes_meeting_point(cameras: list[Camera]) -> Tensor:
    """[3] least-squares point closest to all optical axes (where the cameras look)."""
    A = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for cam in cameras:
        w2c = cam.world_to_cam.double().cpu()
        d = w2c[2, :3]  # optical axis (camera +z) in world
        o = -w2c[:3, :3].T @ w2c[:3, 3]
        P = torch.eye(3, dtype=torch.float64) - torch.outer(d, d)
        A += P
        b += P @ o
    return torch.linalg.lstsq(A, b[:, None]).solution[:, 0]


def hull_bounds(cameras: list[Camera], masks: list[Tensor], resolution: int = 64,
                threshold: float = 0.0) -> tuple[Tensor, Tensor]:
    """Axis-aligned bounds (lo [3], hi [3]) of the visual hull, found on a ``resolution``^3 grid.

    The grid covers a cube around the point the cameras look at, as wide as the widest view frustum
    there. Raises ValueError if no grid point survives (masks empty or cameras inconsistent).
    """
    centre = axes_meeting_point(cameras)
    half = 0.0
    for cam in cameras:
        dist = float((cam.center.double().cpu() - centre).norm())
        half = max(half, dist * max(cam.width / (2 * cam.fx), cam.height / (2 * cam.fy)))
    lin = torch.linspace(-half, half, resolution, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3) + centre
    keep = inside_hull(grid, cameras, masks, threshold)
    if not keep.any():
        raise DatasetError("visual hull is empty: no point projects into the foreground of every training mask")
    pts = grid[keep]
    step = 2 * half / (resolution - 1)
    return pts.min(0).values - step, pts.max(0).values + step


def sample_hull(n: int, cameras: list[Camera], masks: list[Tensor], lo: Tensor, hi: Tensor,
                generator: torch.Generator, threshold: float = 0.0, max_rounds: int = 200) -> Tensor:
    """``n`` points [n, 3] drawn uniformly inside the visual hull within the box [lo, hi].

    Rejection sampling of uniform points in the box. Raises ValueError if the hull is (nearly) empty.
    """
    out: list[Tensor] = []
    count = 0
    lo, hi = lo.double(), hi.double()
    batch = max(4 * n, 65536)
    for _ in range(max_rounds):
        p = lo + (hi - lo) * torch.rand(batch, 3, generator=generator, dtype=torch.float64)
        p = p[inside_hull(p, cameras, masks, threshold)]
        out.append(p)
        count += p.shape[0]
        if count >= n:
            break
    if count == 0:
        raise DatasetError("visual hull sampling found no points inside every training mask")
    pts = torch.cat(out)[:n]
    if pts.shape[0] < n:  # tiny hull: repeat with jitter rather than fail
        idx = torch.randint(pts.shape[0], (n - pts.shape[0],), generator=generator)
        pts = torch.cat([pts, pts[idx]])
    return pts.float()
