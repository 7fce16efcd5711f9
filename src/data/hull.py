"""Visual hulls from calibrated masks: scene normalisation and splat initialisation.

A point belongs to the visual hull if it projects inside every given view's image onto a mask
value above ``threshold`` (nearest pixel). Conventions: OpenCV cameras, pixel (i, j) covers
[i, i+1) x [j, j+1).

A hull that cannot bound the object is refused with a :class:`DatasetError` naming the views used and
what in them looks wrong (:func:`hull_error`): an empty hull (all-zero or inverted masks, cameras not
looking at the object) and the unbounded cone of views that all share one camera position (identical
poses, duplicate frames).
"""

from __future__ import annotations

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.data.base import DatasetError

NAMES_SHOWN = 8  # views named in a hull error before "+N more"
LIKELY_CAUSES = ("identical or duplicate camera poses, all-zero or inverted masks, or cameras not looking at "
                 "the object")


def camera_name(cameras: list[Camera], i: int) -> str:
    """The name of ``cameras[i]`` on one line (``#i`` if it has none)."""
    return " ".join(str(cameras[i].name).split()) or f"#{i}"


def joined(names: list[str], sep: str = ", ") -> str:
    """The first :data:`NAMES_SHOWN` of ``names`` joined by ``sep``, then how many more there are."""
    more = f" (+{len(names) - NAMES_SHOWN} more)" if len(names) > NAMES_SHOWN else ""
    return sep.join(names[:NAMES_SHOWN]) + more


def shared_positions(cameras: list[Camera], rel_tol: float = 1e-6) -> list[list[str]]:
    """Groups (two or more names) of cameras whose centres coincide within ``rel_tol`` of their distance scale."""
    centres = torch.stack([c.center.double().cpu() for c in cameras])
    tol = rel_tol * max(1.0, float(centres.abs().max()))
    groups: list[list[int]] = []
    for i in range(len(cameras)):
        for g in groups:
            if float((centres[g[0]] - centres[i]).abs().max()) <= tol:
                g.append(i)
                break
        else:
            groups.append([i])
    return [[camera_name(cameras, i) for i in g] for g in groups if len(g) > 1]


def mask_findings(cameras: list[Camera], masks: list[Tensor], threshold: float) -> list[str]:
    """What looks wrong in the masks: all background, or foreground along the whole image border (inverted)."""
    empty, inverted = [], []
    for i, mask in enumerate(masks):
        fg = mask.cpu() > threshold
        name = camera_name(cameras, i)
        if not bool(fg.any()):
            empty.append(name)
        elif bool(torch.cat([fg[0], fg[-1], fg[:, 0], fg[:, -1]]).all()):
            inverted.append(name)
    out = []
    if empty:
        out.append(f"all-zero masks in views {joined(empty)}")
    if inverted:
        out.append(f"masks that are foreground along the whole image border (inverted?) in views {joined(inverted)}")
    return out


def axes_define_a_point(cameras: list[Camera], tol: float = 1e-6) -> bool:
    """Do the optical axes define a meeting point (not all parallel)?"""
    if len(cameras) < 2:
        return False
    A = torch.zeros(3, 3, dtype=torch.float64)
    for cam in cameras:
        d = cam.world_to_cam.double().cpu()[2, :3]
        A += torch.eye(3, dtype=torch.float64) - torch.outer(d, d)
    return float(torch.linalg.eigvalsh(A / len(cameras))[0]) > tol


def off_target(cameras: list[Camera]) -> list[str]:
    """Names of the cameras that do not see (in front, inside the image) the point all optical axes meet."""
    if not axes_define_a_point(cameras):
        return []
    point = axes_meeting_point(cameras)
    names = []
    for i, cam in enumerate(cameras):
        uv, z = cam.to("cpu").project(point[None].to(cam.world_to_cam.dtype))
        u, v = float(uv[0, 0]), float(uv[0, 1])
        if not (float(z[0]) > 0 and 0 <= u < cam.width and 0 <= v < cam.height):
            names.append(camera_name(cameras, i))
    return names


def hull_error(problem: str, cameras: list[Camera], masks: list[Tensor], threshold: float = 0.0,
               where: str = "") -> DatasetError:
    """A one-line DatasetError: ``problem``, the views used, what was found wrong in them and the likely causes."""
    found = mask_findings(cameras, masks, threshold)
    shared = shared_positions(cameras)
    found += [f"views {joined(g, ' = ')} share one camera position" for g in shared[:3]]
    if len(shared) > 3:
        found.append(f"{len(shared) - 3} more groups of views share a camera position")
    away = off_target(cameras)
    if away:
        found.append(f"views {joined(away)} do not see the point the cameras' optical axes meet")
    prefix = f"{where}: " if where else ""
    used = joined([camera_name(cameras, i) for i in range(len(cameras))])
    detail = f"; found: {'; '.join(found)}" if found else ""
    return DatasetError(f"{prefix}{problem} (the {len(cameras)} training views used: {used}){detail}; "
                        f"likely causes: {LIKELY_CAUSES}")


def check_viewpoints(cameras: list[Camera], masks: list[Tensor], threshold: float = 0.0, where: str = "") -> None:
    """DatasetError if two or more views all share one camera position: their hull is an unbounded cone."""
    groups = shared_positions(cameras) if len(cameras) >= 2 else []
    if groups and len(groups[0]) == len(cameras):
        raise hull_error("visual hull cannot bound the object: every training view is taken from the same camera "
                         "position", cameras, masks, threshold, where)


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
                threshold: float = 0.0, where: str = "") -> tuple[Tensor, Tensor]:
    """Axis-aligned bounds (lo [3], hi [3]) of the visual hull, found on a ``resolution``^3 grid.

    The grid covers a cube around the point the cameras look at, as wide as the widest view frustum
    there. Raises DatasetError (see :func:`hull_error`, prefixed by ``where``) if every view shares one
    camera position or no grid point survives.
    """
    check_viewpoints(cameras, masks, threshold, where)
    centre = axes_meeting_point(cameras)
    half = 0.0
    for cam in cameras:
        dist = float((cam.center.double().cpu() - centre).norm())
        half = max(half, dist * max(cam.width / (2 * cam.fx), cam.height / (2 * cam.fy)))
    lin = torch.linspace(-half, half, resolution, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(lin, lin, lin, indexing="ij"), -1).reshape(-1, 3) + centre
    keep = inside_hull(grid, cameras, masks, threshold)
    if not keep.any():
        raise hull_error("visual hull is empty: no point projects into the foreground of every training mask",
                         cameras, masks, threshold, where)
    pts = grid[keep]
    step = 2 * half / (resolution - 1)
    return pts.min(0).values - step, pts.max(0).values + step


def sample_hull(n: int, cameras: list[Camera], masks: list[Tensor], lo: Tensor, hi: Tensor,
                generator: torch.Generator, threshold: float = 0.0, max_rounds: int = 200,
                where: str = "") -> Tensor:
    """``n`` points [n, 3] drawn uniformly inside the visual hull within the box [lo, hi].

    Rejection sampling of uniform points in the box. Raises DatasetError (see :func:`hull_error`,
    prefixed by ``where``) if every view shares one camera position or no point lands in the hull.
    """
    check_viewpoints(cameras, masks, threshold, where)
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
        raise hull_error(f"visual hull is empty: none of {max_rounds * batch} points sampled in the box "
                         "projects into the foreground of every training mask", cameras, masks, threshold, where)
    pts = torch.cat(out)[:n]
    if pts.shape[0] < n:  # tiny hull: repeat with jitter rather than fail
        idx = torch.randint(pts.shape[0], (n - pts.shape[0],), generator=generator)
        pts = torch.cat([pts, pts[idx]])
    return pts.float()
