"""A triangle mesh of a trained splat set by screened Poisson reconstruction (``mesh=poisson``, SuGaR).

SuGaR (Guédon and Lepetit, CVPR 2024, Sec. 4.2) reconstructs its mesh by Poisson reconstruction of points
on a level set of the regularised Gaussians' density, seen from the training cameras. Here the points are
sampled on the flat splats themselves: per splat, points of its Gaussian in the plane of its two largest axes,
with its shortest axis as the normal, oriented towards the nearest training camera. Open3D runs the Poisson
reconstruction; it is an optional dependency (``pip install -e ".[mesh]"``): without it, or when it cannot be
loaded (a missing system library), the run records why no mesh was written and goes on.

Conventions: activated splats (linear scales, opacities in (0, 1), (w, x, y, z) quaternions), world frame of
the normalised scene (the frame of ``splats.ply``).
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from src.core.splats import Splats, shortest_axis
from src.fields.flows import quat_to_rotmat_wxyz
from src.utils.record import os_error_line
from src.utils.validate import ConfigValueError

if TYPE_CHECKING:  # annotations only: open3d is optional (pip install -e ".[mesh]")
    import open3d

log = logging.getLogger(__name__)

MESH_PLY = "mesh.ply"
MISSING = 'open3d is not installed (pip install -e ".[mesh]"): no mesh.ply written'
NEAREST_CHUNK = 1 << 20  # points per nearest-camera search ([chunk, C] distances in float64)


def oriented_splat_points(splats: Splats, cameras: Tensor, n_points: int, min_opacity: float,
                          seed: int = 0) -> tuple[Tensor, Tensor]:
    """(points [M, 3], unit normals [M, 3]) sampled on the splats with opacity >= ``min_opacity``.

    Splats are drawn with probability proportional to the product of their two largest scales (their
    area); each point is mu + R (s * eps) with the component along the shortest axis set to 0, so it lies in
    the splat's plane; its normal is that axis, signed to face the nearest of the camera centres
    ``cameras`` [C, 3]. M = ``n_points`` (0 if no splat is kept: none opaque enough with a positive, finite area).
    """
    ordered = splats.scales.double().sort(-1).values
    area = ordered[:, 1] * ordered[:, 2]  # [N] product of the two largest scales
    keep = (splats.opacities >= min_opacity) & torch.isfinite(area) & (area > 0)  # a flat-out splat has no area
    means, scales, area = splats.means[keep].double(), splats.scales[keep].double(), area[keep]  # [K, 3], [K]
    if means.shape[0] == 0 or n_points <= 0:
        empty = torch.zeros(0, 3, dtype=torch.float64)
        return empty, empty
    rotations = quat_to_rotmat_wxyz(splats.quats[keep].double())  # [K, 3, 3]
    _, shortest, axes = shortest_axis(rotations, scales)  # [K], [K, 3]
    g = torch.Generator().manual_seed(int(seed))
    pick = torch.multinomial(area / area.sum(), int(n_points), replacement=True, generator=g)  # [M]
    eps = torch.randn(int(n_points), 3, generator=g, dtype=torch.float64)
    eps.scatter_(1, shortest[pick][:, None], 0.0)  # in the splat's plane
    points = means[pick] + torch.einsum("mij,mj->mi", rotations[pick], scales[pick] * eps)
    normals = axes[pick]  # [M, 3]
    cams = cameras.double()
    nearest = torch.cat([torch.cdist(chunk, cams).argmin(-1) for chunk in points.split(NEAREST_CHUNK)])  # [M]
    sign = torch.sign(((cams[nearest] - points) * normals).sum(-1))
    return points, normals * torch.where(sign == 0, torch.ones_like(sign), sign)[:, None]


def _write_atomic(o3d, mesh, path: Path) -> None:
    """Write ``mesh`` to ``path`` through a temporary file in the same folder (readers never see half a mesh;
    a failed write leaves neither ``path`` nor the temporary file)."""
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh):
            raise RuntimeError(f"open3d could not write {path} (through {tmp.name})")
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


class PoissonMesh:
    """Poisson reconstruction of points sampled on the trained splats, written as ``<run>/mesh.ply``.

    Args:
        n_points: points sampled on the splats (SuGaR's extractor: ``n_total_points`` 10^7 level-set points
            over all views).
        poisson_depth: octree depth of the reconstruction (SuGaR's extractor: 10, "6 or 7 work well for most
            synthetic scenes").
        density_quantile: remove the vertices whose Poisson density is below this quantile (SuGaR's extractor:
            0.1 for real scenes, 0 for synthetic ones); in [0, 1).
        min_opacity: sample only splats with at least this opacity (SuGaR's prune threshold: 0.5); in [0, 1].
        decimation_target: decimate to at most this many triangles (SuGaR's extractor: 200 000 or 1 000 000;
            null: never); >= 1.
        seed: seed of the point sampling.

    Raises:
        ConfigValueError: a value out of range, naming its ``mesh.`` key.
    """

    def __init__(self, n_points: int = 10_000_000, poisson_depth: int = 10, density_quantile: float = 0.1,
                 min_opacity: float = 0.5, decimation_target: int | None = 200_000, seed: int = 0) -> None:
        checks = (("n_points", n_points, n_points >= 1, "an integer >= 1"),
                  ("poisson_depth", poisson_depth, poisson_depth >= 1, "an integer >= 1"),
                  ("density_quantile", density_quantile, 0.0 <= density_quantile < 1.0, "a value in [0, 1)"),
                  ("min_opacity", min_opacity, 0.0 <= min_opacity <= 1.0, "a value in [0, 1]"),
                  ("decimation_target", decimation_target, decimation_target is None or decimation_target >= 1,
                   "an integer >= 1 or null"))
        for key, value, ok, expected in checks:
            if not ok:
                raise ConfigValueError(f"mesh.{key}={value!r}: expected {expected}")
        self.n_points, self.depth = int(n_points), int(poisson_depth)
        self.density_quantile, self.min_opacity = float(density_quantile), float(min_opacity)
        self.decimation_target = None if decimation_target is None else int(decimation_target)
        self.seed = int(seed)

    def reconstruct(self, points: Tensor, normals: Tensor) -> open3d.geometry.TriangleMesh:
        """An open3d ``TriangleMesh`` of oriented points [M, 3] (raises ImportError without open3d)."""
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.double().cpu().numpy()))
        cloud.normals = o3d.utility.Vector3dVector(normals.double().cpu().numpy())
        mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=self.depth)
        densities = np.asarray(densities)
        if self.density_quantile > 0 and densities.size:
            mesh.remove_vertices_by_mask(densities < np.quantile(densities, self.density_quantile))
        if self.decimation_target is not None and len(mesh.triangles) > self.decimation_target:
            mesh = mesh.simplify_quadric_decimation(self.decimation_target)
        return mesh

    def write(self, splats: Splats, cameras: Tensor, run_dir: Path | str) -> dict:
        """Write ``<run_dir>/mesh.ply`` from baked ``splats`` and training camera centres [C, 3].

        Returns the run record's ``mesh`` entry: ``written``, and ``file``, ``n_vertices``, ``n_triangles``,
        ``mesh_s`` when written, else ``reason`` (logged in one line; the run goes on): open3d missing, or
        present but not loadable (an OSError from a missing system library such as ``libusb-1.0``).
        """
        t0 = time.perf_counter()
        try:
            import open3d as o3d
        except ImportError:
            log.warning("mesh=poisson: %s", MISSING)
            return {"written": False, "reason": MISSING}
        except OSError as e:
            reason = f"open3d cannot be loaded ({' '.join(os_error_line(e).split())[:200]}): no mesh.ply written"
            log.warning("mesh=poisson: %s", reason)
            return {"written": False, "reason": reason}
        points, normals = oriented_splat_points(splats.detach().to("cpu"), cameras.detach().cpu(), self.n_points,
                                                self.min_opacity, self.seed)
        if points.shape[0] == 0:
            reason = f"no splat with opacity >= {self.min_opacity} and a positive area: no mesh.ply written"
            log.warning("mesh=poisson: %s", reason)
            return {"written": False, "reason": reason}
        try:
            mesh = self.reconstruct(points, normals)
            path = Path(run_dir) / MESH_PLY
            _write_atomic(o3d, mesh, path)
        except (RuntimeError, ValueError, OSError) as e:
            reason = f"Poisson reconstruction failed ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
            log.warning("mesh=poisson: %s", reason)
            return {"written": False, "reason": reason}
        return {"written": True, "file": MESH_PLY, "n_vertices": len(mesh.vertices),
                "n_triangles": len(mesh.triangles), "mesh_s": time.perf_counter() - t0}


__all__ = ["MESH_PLY", "PoissonMesh", "oriented_splat_points"]
