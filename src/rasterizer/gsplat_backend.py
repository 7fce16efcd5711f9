"""CUDA rasterizer: a thin wrapper of ``gsplat.rasterization`` (optional extra ``[cuda]``).

Importing this module does not import gsplat; constructing :class:`GsplatRasterizer` does, and needs CUDA.
Semantic differences from the 3DGS rules that ``torch_ref``/``cpu`` follow, and how they are reconciled:

* pixel centres: gsplat samples pixel (i, j) at (i + 0.5, j + 0.5) and projects u = fx x / z + cx, the
  same convention as this project: nothing to reconcile.
* near plane: 3DGS culls splats with z <= 0.2; ``near_plane`` defaults to 0.2 here (gsplat: 0.01).
* low-pass filter ``eps2d`` = 0.3 in both; with ``antialiased`` gsplat's ``rasterize_mode="antialiased"``
  with ``eps2d`` = ``filter_2d`` (Mip-Splatting's 2D Mip filter: Sigma2D + 0.1 I, opacities times
  sqrt(det(Sigma2D) / det(Sigma2D + 0.1 I)), as the ``antialiased`` cpu and torch_ref backends).
* radius / tile rule: gsplat bounds splats by ~3.33 sigma per axis instead of 3 sqrt(lambda_max), and its
  alpha clamp (0.99 in its CUDA kernel; 0.999 in its torch reference) and transmittance cut-off may
  differ; renders agree with ``torch_ref`` up to these border effects (GPU-only parity test).
* depth: gsplat's "RGB+ED" gives the alpha-normalised expected depth; it is multiplied by alpha here so
  ``RenderOutput.depth`` is the accumulated sum z alpha T like the other backends.
* view-space gradient: gsplat's projected centres ``meta["means2d"]`` [1, N, 2] lie on the image's
  autograd graph, but a slice of them taken after rendering does not, so its ``.grad`` would stay empty
  and adaptive density control would never densify. ``RenderOutput.means2d`` is therefore a leaf
  whose ``.grad`` a hook on the graph's tensor fills (:func:`~src.rasterizer.base.gradient_leaf`), as the other
  backends' ``means2d.grad``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats
from src.rasterizer.base import Rasterizer, check_surfels, gradient_leaf


class GsplatRasterizer(Rasterizer):
    """gsplat's CUDA rasterization behind the project's :class:`Rasterizer` interface.

    Args:
        near_plane: cull splats closer than this (3DGS: 0.2).
        antialiased: Mip-Splatting's 2D Mip filter (gsplat ``rasterize_mode="antialiased"``) instead of
            3DGS's dilation (``classic``).
        filter_2d: variance (pixels^2) of the 2D Mip filter, gsplat's ``eps2d`` when ``antialiased``
            (Mip-Splatting: 0.1).
        surfels: 2D Gaussian surfels (2DGS) with ``gsplat.rasterization_2dgs``
            (:func:`~src.rasterizer.gsplat_surfel.render_surfels_gsplat`).
    """

    name = "gsplat"

    def __init__(self, near_plane: float = 0.2, antialiased: bool = False, filter_2d: float = 0.1,
                 surfels: bool = False) -> None:
        if not torch.cuda.is_available():
            raise RuntimeError("rasterizer=gsplat needs a CUDA GPU; use rasterizer=cpu or rasterizer=auto")
        try:
            import gsplat  # noqa: F401
        except ImportError as e:
            raise ImportError("rasterizer=gsplat needs the optional extra: pip install -e '.[cuda]'") from e
        self.near_plane = near_plane
        self.antialiased = bool(antialiased)
        self.eps2d = float(filter_2d) if self.antialiased else 0.3
        self.rasterize_mode = "antialiased" if self.antialiased else "classic"
        self.surfels = check_surfels(surfels, antialiased)

    def render(self, splats: Splats, camera: Camera, background: Tensor | None = None) -> RenderOutput:
        if self.surfels:
            from src.rasterizer.gsplat_surfel import render_surfels_gsplat

            return render_surfels_gsplat(splats, camera, background, near_plane=self.near_plane)
        from gsplat import rasterization

        splats.validate()
        dev = splats.means.device
        C = splats.colors.shape[1]
        bg = torch.zeros(C, device=dev) if background is None else background.to(dev, splats.means.dtype)
        K = camera.K.to(dev, splats.means.dtype)[None]
        view = camera.world_to_cam.to(dev, splats.means.dtype)[None]
        colors, alphas, meta = rasterization(
            splats.means, torch.nn.functional.normalize(splats.quats, dim=-1), splats.scales, splats.opacities,
            splats.colors, view, K, camera.width, camera.height, near_plane=self.near_plane, eps2d=self.eps2d,
            packed=False, render_mode="RGB+ED", rasterize_mode=self.rasterize_mode, backgrounds=None,
        )
        alpha = alphas[0, ..., 0]
        color = colors[0, ..., :C] + (1 - alpha)[..., None] * bg
        depth = colors[0, ..., C] * alpha
        means2d = gradient_leaf(meta["means2d"])  # [N, 2], .grad: the view-space gradient (pixels)
        radii = meta["radii"][0]
        if radii.ndim == 2:  # newer gsplat: per-axis radii
            radii = radii.max(dim=-1).values
        return RenderOutput(color=color, alpha=alpha, depth=depth, means2d=means2d, radii=radii.to(torch.int32))
