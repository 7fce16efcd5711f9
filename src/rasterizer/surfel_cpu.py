"""Compiled CPU compositing of 2D Gaussian surfels (2DGS) with a hand-written backward.

Same semantics as :func:`~src.rasterizer.surfel_ref.render_surfels_ref` (see
:mod:`src.rasterizer.surfel_ref`): the projection (the ray-splat intersection matrices T, projected
centres and oriented normals) is the torch one, differentiated by autograd; the depth sort, tile
binning and compositing of colours, depth, normals and the depth distortion run in
``csrc/surfel_cpu.cpp`` (float32 and float64), whose backward returns the gradients w.r.t. T, the
projected centres, the normals, the opacities and the colours. The extension is built on the first
render (:func:`~src.kernels.build.load_surfel_extension`), never at import.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats, SurfelRenderOutput
from src.kernels.build import load_surfel_extension
from src.rasterizer.surfel_ref import project_surfels


class _SurfelComposite(torch.autograd.Function):
    """Composite projected surfels; differentiable in transforms, means2d, normals, opacities, colors, background.

    Inputs (one dtype, float32 or float64, contiguous, CPU): transforms [N, 9], means2d [N, 2], normals [N, 3],
    opacities [N], colors [N, C], rects [N, 4] int32, depths [N] (sort key, not differentiated: it is
    T_w[2], whose gradient reaches ``transforms``), visible [N] bool, background [C].
    Outputs: color [H, W, C], alpha [H, W], depth [H, W], normals [H, W, 3], distortion [H, W].
    """

    @staticmethod
    def forward(ctx: Any, transforms: Tensor, means2d: Tensor, normals: Tensor, opacities: Tensor,  # type: ignore[override]
                colors: Tensor, rects: Tensor, depths: Tensor, visible: Tensor, background: Tensor,
                width: int, height: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        ext = load_surfel_extension()
        (color, alpha, depth, nrm, dist, t_final, m1, m2, last, offsets, lists) = ext.surfel_forward(
            transforms, means2d, normals, opacities, colors, rects, depths, visible, background, width, height)
        ctx.save_for_backward(transforms, means2d, normals, opacities, colors, rects, background, t_final, m1, m2,
                              last, offsets, lists)
        ctx.size = (width, height)
        return color, alpha, depth, nrm, dist

    @staticmethod
    def backward(ctx: Any, g_color: Tensor, g_alpha: Tensor, g_depth: Tensor, g_normals: Tensor,  # type: ignore[override]
                 g_dist: Tensor):
        ext = load_surfel_extension()
        (transforms, means2d, normals, opacities, colors, rects, background, t_final, m1, m2, last, offsets,
         lists) = ctx.saved_tensors
        width, height = ctx.size
        C = colors.shape[1]
        P = width * height

        def flat(g: Tensor, cols: int) -> Tensor:  # [P] or [P, cols], contiguous, zeros where unused
            if g is None:
                return torch.zeros((P, cols) if cols else (P,), dtype=transforms.dtype)
            return g.reshape((P, cols) if cols else (P,)).to(transforms.dtype).contiguous()

        gT, gc, gn, go, gcol = ext.surfel_backward(
            flat(g_color, C), flat(g_alpha, 0), flat(g_depth, 0), flat(g_normals, 3), flat(g_dist, 0), transforms,
            means2d, normals, opacities, colors, rects, background, t_final.reshape(-1), m1.reshape(-1),
            m2.reshape(-1), last.reshape(-1), offsets, lists, width, height)
        g_bg = None
        if ctx.needs_input_grad[8] and g_color is not None:
            g_bg = (g_color * t_final[..., None]).sum(dim=(0, 1))
        return gT, gc, gn, go, gcol, None, None, None, g_bg, None, None


def check_surfel_inputs(splats: Splats, camera: Camera, background: Tensor | None) -> None:
    """Raise ValueError / TypeError unless the splats, camera and background suit the CPU surfel kernel."""
    splats.validate()
    for name in ("means", "scales", "quats", "opacities", "colors"):
        t = getattr(splats, name)
        if t.device.type != "cpu":
            raise ValueError(f"the cpu surfel rasterizer needs CPU tensors; Splats.{name} is on {t.device}")
        if t.dtype not in (torch.float32, torch.float64) or t.dtype != splats.means.dtype:
            raise TypeError(f"the cpu surfel rasterizer needs float32 or float64 splats of one dtype; "
                            f"Splats.{name} is {t.dtype}")
    if camera.width <= 0 or camera.height <= 0:
        raise ValueError(f"bad image size {camera.width}x{camera.height}")
    if background is not None and background.shape != (splats.colors.shape[1],):
        raise ValueError(f"background has shape {tuple(background.shape)}, expected ({splats.colors.shape[1]},)")


def render_surfels_cpu(splats: Splats, camera: Camera, background: Tensor | None = None) -> SurfelRenderOutput:
    """Render ``splats`` as 2D Gaussian surfels with the compiled kernel (same results as the torch reference).

    Args:
        splats: N activated splats on the CPU (float32 or float64); ``scales[:, :2]`` are (s_u, s_v).
        camera: OpenCV pinhole camera.
        background: [C] colour weighted by T_final (zeros if None).
    Returns:
        SurfelRenderOutput (colour, alpha, depth, world normals, distortion, means2d, radii).
    """
    check_surfel_inputs(splats, camera, background)
    dtype = splats.means.dtype
    C = splats.colors.shape[1]
    bg = torch.zeros(C, dtype=dtype) if background is None else background.to(dtype=dtype)
    proj = project_surfels(splats.means, splats.quats, splats.scales, camera)
    color, alpha, depth, normals, dist = _SurfelComposite.apply(
        proj.transforms.contiguous(), proj.means2d.contiguous(), proj.normals.contiguous(),
        splats.opacities.contiguous(), splats.colors.contiguous(), proj.rects.contiguous(),
        proj.depths.detach().contiguous(), proj.visible.contiguous(), bg.contiguous(), camera.width, camera.height)
    return SurfelRenderOutput(color=color, alpha=alpha, depth=depth, means2d=proj.means2d, radii=proj.radii,
                              normals=normals, distortion=dist)
