"""2D Gaussian surfels on CUDA: a thin wrapper of ``gsplat.rasterization_2dgs`` (optional extra ``[cuda]``).

Used by :class:`~src.rasterizer.gsplat_backend.GsplatRasterizer` with ``surfels=True``. Importing this module
does not import gsplat. It follows gsplat's documented API and is not exercised by the CPU test suite.
Differences from the CPU backends (:mod:`src.rasterizer.surfel_ref`), not reconciled:

* depth: gsplat composites the surfel centres' camera depths ("RGB+ED"; normalised by alpha, multiplied
  back by alpha here so ``depth`` is sum z alpha T like the other backends), not the ray-splat
  intersection depths;
* distortion: gsplat's map is the L1 form sum w_i w_j |z_i - z_j| of its raw camera depths, not the
  squared NDC-depth form of the 2DGS reference code; the render says so (``distortion_form="depth_l1"``)
  and :class:`~src.losses.surfel.SurfelLoss` weighs it with its own ``lambda_dist_l1``;
* the low-pass filter, tile rule and alpha rules are gsplat's.

``means2d`` is a leaf tensor whose ``.grad``, after the backward, holds gsplat's 2DGS densification
gradient (``meta["gradient_2dgs"]``, the counterpart of 3DGS's view-space gradient), so the ADC strategy
reads it as it reads the 3DGS backends' ``means2d.grad``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats, SurfelRenderOutput
from src.rasterizer.base import gradient_leaf


def render_surfels_gsplat(splats: Splats, camera: Camera, background: Tensor | None = None,
                          near_plane: float = 0.2, far_plane: float = 100.0) -> SurfelRenderOutput:
    """Render ``splats`` as 2D Gaussian surfels with gsplat's CUDA 2DGS rasterization.

    Args:
        splats: N activated splats on a CUDA device; ``scales[:, :2]`` are the tangent scales, quaternions wxyz.
        camera: OpenCV pinhole camera.
        background: [C] colour weighted by 1 - alpha (zeros if None).
        near_plane, far_plane: gsplat's clipping planes (near 0.2 as 3DGS; far: the 2DGS reference's 100).
    Returns:
        SurfelRenderOutput with world-frame normals (gsplat rotates its rendered normals to the world).
    """
    from gsplat import rasterization_2dgs

    splats.validate()
    dev, dt = splats.means.device, splats.means.dtype
    C = splats.colors.shape[1]
    bg = torch.zeros(C, device=dev, dtype=dt) if background is None else background.to(dev, dt)
    K = camera.K.to(dev, dt)[None]  # [1, 3, 3]
    view = camera.world_to_cam.to(dev, dt)[None]  # [1, 4, 4]
    colors, alphas, normals, _surf_normals, distort, _median, meta = rasterization_2dgs(
        splats.means, torch.nn.functional.normalize(splats.quats, dim=-1), splats.scales, splats.opacities,
        splats.colors[None], view, K, camera.width, camera.height, near_plane=near_plane, far_plane=far_plane,
        packed=False, render_mode="RGB+ED", distloss=True, backgrounds=None,
    )
    alpha = alphas[0, ..., 0]  # [H, W]
    color = colors[0, ..., :C] + (1 - alpha)[..., None] * bg
    depth = colors[0, ..., C] * alpha
    radii = meta["radii"][0]
    if radii.ndim == 2:  # newer gsplat: per-axis radii
        radii = radii.max(dim=-1).values
    # [N, 2] leaf of the projected centres; its .grad: gsplat's 2DGS densification gradient (camera 0)
    means2d = gradient_leaf(meta["means2d"], meta.get("gradient_2dgs"))
    return SurfelRenderOutput(color=color, alpha=alpha, depth=depth, means2d=means2d, radii=radii.to(torch.int32),
                              normals=normals[0], distortion=distort[0, ..., 0], distortion_form="depth_l1")
