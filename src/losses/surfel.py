"""The geometry regularisers of 2D Gaussian Splatting (Huang et al., SIGGRAPH 2024, Sec. 4.1) on top of eq. A.2.

* depth distortion (Eq. 13): the mean over pixels of the surfel rasterizer's distortion map
  sum_{j<i} w_i w_j (m_i - m_j)^2 (:class:`~src.core.splats.SurfelRenderOutput`);
* normal consistency (Eq. 14): the mean over pixels of 1 - n_rendered . N_depth, where n_rendered is the
  accumulated (unnormalised) surfel normal and N_depth the normal of the surface given by the expected
  depth (depth / alpha), from central finite differences of its back-projected points, times the
  detached alpha (the reference code's ``surf_normal * alpha.detach()``; its border pixels are zero).

Both start after an iteration offset (the reference code: distortion after 3 000, normals after 7 000 of
30 000 iterations), given by ``schedule.gs2d_dist_from`` / ``schedule.gs2d_normal_from`` per scale.
Conventions: OpenCV cameras (x right, y down, z forward), world-frame normals, images [H, W, C].
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats, SurfelRenderOutput
from src.data.base import View
from src.losses.objective import SplatLoss


def depth_normals(depth: Tensor, alpha: Tensor, camera: Camera) -> Tensor:
    """World-frame normals [H, W, 3] of the surface given by the expected depth ``depth / alpha``.

    The pixel (i, j) back-projects to z ((i + 0.5 - cx) / fx, (j + 0.5 - cy) / fy, 1) in the camera frame;
    the normal is normalise(dP/dy x dP/dx) from central differences (2DGS reference ``depth_to_normal``),
    which points towards the camera for a surface facing it; border pixels get zeros.

    Args:
        depth: [H, W] accumulated depth sum z w (as every rasterizer here returns it); alpha: [H, W].
        camera: the OpenCV camera of the render.
    """
    H, W = depth.shape
    z = torch.where(alpha > 0, depth / torch.where(alpha > 0, alpha, torch.ones_like(alpha)), torch.zeros_like(depth))
    xs = (torch.arange(W, device=depth.device, dtype=depth.dtype) + 0.5 - camera.cx) / camera.fx  # [W]
    ys = (torch.arange(H, device=depth.device, dtype=depth.dtype) + 0.5 - camera.cy) / camera.fy  # [H]
    pts = torch.stack([xs[None, :] * z, ys[:, None] * z, z], dim=-1)  # [H, W, 3] camera frame
    d_y = pts[2:, 1:-1] - pts[:-2, 1:-1]  # along the image rows (y)
    d_x = pts[1:-1, 2:] - pts[1:-1, :-2]  # along the image columns (x)
    n = F.normalize(torch.linalg.cross(d_y, d_x, dim=-1), dim=-1)
    R = camera.world_to_cam[:3, :3].to(device=depth.device, dtype=depth.dtype)
    return F.pad((n @ R).permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)  # world frame: R^T n


def normal_consistency(render: SurfelRenderOutput, camera: Camera) -> Tensor:
    """2DGS Eq. 14: mean over pixels of 1 - n_rendered . (N_depth x alpha.detach())."""
    surf = depth_normals(render.depth, render.alpha, camera) * render.alpha.detach()[..., None]
    return (1.0 - (render.normals * surf).sum(-1)).mean()


class SurfelLoss(SplatLoss):
    """eq. A.2 (:class:`SplatLoss`) + lambda_dist L_d (2DGS Eq. 13) + lambda_normal L_n (2DGS Eq. 14).

    Args:
        lambda_dist: weight of the depth distortion in the 2DGS reference's squared NDC-depth form (2DGS:
            1000 for bounded / object scenes, 100 unbounded).
        lambda_dist_l1: weight of the distortion in gsplat's L1 raw-depth form (renders with
            ``distortion_form="depth_l1"``; gsplat's own 2DGS trainer uses 1e-3).
        lambda_normal: weight of the normal consistency (2DGS: 0.05).
        dist_from / normal_from: the terms act from these (0-based) iterations on (2DGS reference: after
            iteration 3 000 / 7 000).
        **kwargs: the arguments of :class:`SplatLoss`.
    """

    def __init__(self, lambda_dist: float = 1000.0, lambda_normal: float = 0.05, dist_from: int = 3000,
                 normal_from: int = 7000, lambda_dist_l1: float = 1e-3, **kwargs) -> None:
        super().__init__(**kwargs)
        self.lambda_dist = float(lambda_dist)
        self.lambda_dist_l1 = float(lambda_dist_l1)
        self.lambda_normal = float(lambda_normal)
        self.dist_from = int(dist_from)
        self.normal_from = int(normal_from)

    def __call__(self, renders: list[RenderOutput], views: list[View], splats: list[Splats],
                 iteration: int = 0) -> dict[str, Tensor]:
        """Loss terms of :class:`SplatLoss` plus 'dist' and 'normal' once they act, and 'total'."""
        dist_on = self.lambda_dist > 0 or self.lambda_dist_l1 > 0
        if (dist_on or self.lambda_normal > 0) and not all(
                isinstance(r, SurfelRenderOutput) for r in renders):
            raise TypeError("the 2DGS losses need surfel renders (normals, distortion): set rasterizer.surfels=true "
                            "(+experiment=gs2d does), or turn them off with loss.lambda_dist=0 loss.lambda_dist_l1=0 "
                            "loss.lambda_normal=0")
        terms = super().__call__(renders, views, splats, iteration=iteration)
        total = terms["total"]
        n = len(renders)
        if dist_on and iteration >= self.dist_from:
            weights = {"ndc_squared": self.lambda_dist, "depth_l1": self.lambda_dist_l1}
            unknown = {r.distortion_form for r in renders} - weights.keys()
            if unknown:
                raise ValueError(f"unknown distortion_form {sorted(unknown)}; expected one of {sorted(weights)}")
            weighted = [(weights[r.distortion_form], r.distortion.mean()) for r in renders]
            terms["dist"] = sum(d for _, d in weighted) / n
            total = total + sum(w * d for w, d in weighted) / n
        if self.lambda_normal > 0 and iteration >= self.normal_from:
            nc = sum(normal_consistency(r, v.camera) for r, v in zip(renders, views, strict=True)) / n
            terms["normal"] = nc
            total = total + self.lambda_normal * nc
        terms["total"] = total
        return terms
