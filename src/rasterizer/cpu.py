"""Compiled CPU rasterizer (C++/OpenMP, 8-lane SIMD) with a hand-written backward.

Same semantics as :class:`~src.rasterizer.torch_ref.TorchRefRasterizer` (the 3DGS CUDA rules; see
:mod:`src.rasterizer`), 1-2 orders of magnitude faster and with O(pixels + splats + tile pairs)
memory. Two compiled parts, each with a hand-written backward:

* the EWA projection (:func:`~src.rasterizer.projection_cpu.project_splats_fused`, bit-identical
  forward to the torch :func:`project_splats`; ``projection="torch"`` selects the latter);
* the depth sort, tile binning and compositing of (means2d, conics, opacities, features) with the
  depth appended as an extra feature channel, the background term and alpha = 1 - T_final (backward
  also w.r.t. the background).

``antialiased=True`` replaces 3DGS's screen-space dilation by Mip-Splatting's 2D Mip filter (the
projection's compensation multiplies the opacities before compositing; same semantics as
``TorchRefRasterizer(antialiased=True)``).

The extension is built on the first render (or :func:`ensure_built`), never at import; see
:mod:`src.kernels.build` for the cache location and flags.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats
from src.kernels.build import load_extension, load_surfel_extension
from src.rasterizer.base import Rasterizer, check_surfels
from src.rasterizer.projection import project_for_render, project_splats
from src.rasterizer.projection_cpu import project_splats_fused

PROJECTIONS = ("fused", "torch")


def ensure_built(verbose: bool = False) -> None:
    """Compile/load the extension now (otherwise it happens on the first render)."""
    load_extension(verbose=verbose)


class _RasterizeFunction(torch.autograd.Function):
    """Composite depth-sorted splats; differentiable in means2d, conics, opacities, colors, depths, background.

    Inputs (float32, contiguous, CPU): means2d [N, 2], conics [N, 3], opacities [N], colors [N, C],
    depths [N] (both the sort key and the composited depth feature; the features composited are
    [colors, depths], NF = C + 1, without materialising their concatenation), radii [N] int32,
    visible [N] bool, background [C].
    Outputs: color [H, W, C] = sum_j c_j alpha_j T_j + T_final bg, alpha [H, W] = 1 - T_final,
    depth [H, W] = sum_j z_j alpha_j T_j, stats [17] float64 (non-differentiable; see
    rasterize_cpu.cpp ``forward``).
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        colors: Tensor,
        depths: Tensor,
        radii: Tensor,
        visible: Tensor,
        background: Tensor,
        width: int,
        height: int,
        cull: bool,
        count: bool,
        first_window: int,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        ext = load_extension()
        out = ext.forward(means2d, conics, opacities, colors, depths, radii, visible, background,
                          width, height, cull, count, first_window)
        color, alpha, depth, t_final, last, *state, stats = out
        ctx.save_for_backward(background, t_final, last, *state)
        ctx.stats = stats
        ctx.n_splats = means2d.shape[0]
        ctx.count = count
        ctx.mark_non_differentiable(stats)
        return color, alpha, depth, stats

    @staticmethod
    def backward(ctx: Any, grad_color: Tensor, grad_alpha: Tensor, grad_depth: Tensor,  # type: ignore[override]
                 _grad_stats: Tensor):
        ext = load_extension()
        background, t_final, last, *state = ctx.saved_tensors
        # original order: g_geo [N, 6] (means2d, conics, depths), g_opacity [N], g_color [N, C]
        g_geo, g_opacity, g_color = ext.backward(
            grad_color.contiguous(), grad_alpha.contiguous(), grad_depth.contiguous(), background,
            t_final, last, *state, ctx.stats, ctx.n_splats, ctx.count)
        grad_bg = None
        if ctx.needs_input_grad[7]:
            grad_bg = (grad_color * t_final[..., None]).sum(dim=(0, 1))
        # strided views of g_geo (no copies; the fused projection backward reads strided rows)
        return (g_geo[:, 0:2], g_geo[:, 2:5], g_opacity, g_color, g_geo[:, 5], None, None, grad_bg,
                None, None, None, None, None)


def _check_inputs(splats: Splats, camera: Camera, background: Tensor | None) -> None:
    splats.validate()
    tensors = {"means": splats.means, "scales": splats.scales, "quats": splats.quats,
               "opacities": splats.opacities, "colors": splats.colors}
    for name, t in tensors.items():
        if t.device.type != "cpu":
            raise ValueError(f"CpuRasterizer needs CPU tensors; Splats.{name} is on {t.device} "
                             "(use rasterizer=gsplat on CUDA)")
        if t.dtype != torch.float32:
            raise TypeError(f"CpuRasterizer supports float32 only; Splats.{name} is {t.dtype} "
                            "(use TorchRefRasterizer for float64)")
    if camera.world_to_cam.device.type != "cpu":
        raise ValueError(f"CpuRasterizer needs a CPU camera; world_to_cam is on {camera.world_to_cam.device}")
    if camera.width <= 0 or camera.height <= 0:
        raise ValueError(f"bad image size {camera.width}x{camera.height}")
    if background is not None:
        if background.device.type != "cpu":
            raise ValueError(f"background must be a CPU tensor, got {background.device}")
        if background.shape != (splats.colors.shape[1],):
            raise ValueError(f"background has shape {tuple(background.shape)}, "
                             f"expected ({splats.colors.shape[1]},)")


class CpuRasterizer(Rasterizer):
    """Compiled C++/OpenMP rasterizer with the torch reference's semantics (float32, CPU).

    Args:
        cull: exact opacity-aware culling (tile binning and per-half-row). It never changes the
            result (bit-identical images and gradients); False only for tests and benchmarks.
        count_pairs: count (pixel, splat) pairs that blend and evaluated vectors into
            :attr:`last_stats` (costs a few percent).
        projection: ``"fused"`` (default): the compiled projection with its hand-written backward;
            ``"torch"``: the elementwise torch-autograd projection (same forward bit for bit,
            gradients equal up to float rounding; for comparisons and benchmarks).
        first_window: about this many splats, the nearest (below a depth quantile estimated
            from a sample), form the first depth window of the forward; of the splats behind it
            only those whose tile rect still meets a tile with live pixels are sorted, and binned
            in windows of twice as many each; 0 (default): max(16384, visible splats / 16), and all
            the remaining splats at once when after a window fewer than 1/8 of the image's
            half-rows have terminated. The windows never change the result (bit-identical to one
            window, tested); a value >= the number of splats gives the plain single binning.
        antialiased: Mip-Splatting's 2D Mip filter (Yu et al. 2024, Sec. 5.2) instead of 3DGS's
            0.3 px^2 dilation: Sigma2D + filter_2d I, opacities times
            sqrt(det(Sigma2D) / det(Sigma2D + filter_2d I)).
        filter_2d: variance (pixels^2) of the 2D Mip filter (Mip-Splatting: 0.1); unused unless
            ``antialiased``.
        surfels: render the splats as 2D Gaussian surfels by ray-splat intersection (2DGS, Huang et al.
            2024) with the compiled surfel kernel (:func:`~src.rasterizer.surfel_cpu.render_surfels_cpu`,
            float32 or float64; returns a :class:`~src.core.splats.SurfelRenderOutput`); the other
            options then do not apply, and ``antialiased`` is refused.

    Attributes:
        last_stats: after a render (and its backward), a dict with ``contrib_pairs`` (pairs with
            alpha >= 1/255 before termination), ``eval_fwd``/``eval_bwd`` (pixel-splat pairs whose
            alpha was computed, 8 per vector; vectors skipped after their power are not counted),
            ``tile_pairs`` (binned (splat, tile) pairs), ``depth_windows``
            and stage times in ms (``sort_ms``: depth sorts and the scan selecting the splats
            behind the first window; ``pack_ms``: raw per-splat records with their tile
            rects, per-tile state, concatenating the windows' tile lists and writing the images;
            ``bin_ms``: gathering, cull geometry and binning per depth window;
            ``raster_fwd_ms``, ``raster_bwd_ms``, ``reduce_ms``; wall clock) and the same with
            ``_cpu_ms`` (process CPU time, all threads).
    """

    name = "cpu"

    def __init__(self, cull: bool = True, count_pairs: bool = False, projection: str = "fused",
                 first_window: int = 0, antialiased: bool = False, filter_2d: float = 0.1,
                 surfels: bool = False) -> None:
        if projection not in PROJECTIONS:
            raise ValueError(f"projection must be one of {PROJECTIONS}, got {projection!r}")
        self.first_window = int(first_window)
        self.cull = bool(cull)
        self.count_pairs = bool(count_pairs)
        self.projection = projection
        self.antialiased = bool(antialiased)
        self.filter_2d = float(filter_2d)
        self.surfels = check_surfels(surfels, antialiased)
        self._stats: Tensor | None = None

    def ensure_built(self, verbose: bool = False) -> None:
        """Compile/load the extension now (e.g. before timing); see :func:`ensure_built`."""
        if self.surfels:
            load_surfel_extension(verbose=verbose)
        else:
            ensure_built(verbose=verbose)

    @property
    def last_stats(self) -> dict[str, float]:
        if self._stats is None:
            return {}
        s = self._stats.tolist()
        return {"contrib_pairs": s[0], "eval_fwd": 8 * s[1], "eval_bwd": 8 * s[2], "tile_pairs": s[3],
                "sort_ms": s[4], "pack_ms": s[5], "bin_ms": s[6], "raster_fwd_ms": s[7],
                "raster_bwd_ms": s[8], "reduce_ms": s[9],
                "sort_cpu_ms": s[10], "pack_cpu_ms": s[11], "bin_cpu_ms": s[12],
                "raster_fwd_cpu_ms": s[13], "raster_bwd_cpu_ms": s[14], "reduce_cpu_ms": s[15], "depth_windows": s[16]}

    def render(self, splats: Splats, camera: Camera, background: Tensor | None = None) -> RenderOutput:
        """Render splats (see :class:`Rasterizer`). Differentiable via the compiled backward."""
        if self.surfels:
            from src.rasterizer.surfel_cpu import render_surfels_cpu

            return render_surfels_cpu(splats, camera, background)
        _check_inputs(splats, camera, background)
        dtype = torch.float32
        W, H = camera.width, camera.height
        C = splats.colors.shape[1]
        if background is None:
            background = torch.zeros(C, dtype=dtype)
        background = background.to(dtype=dtype)

        project = project_splats_fused if self.projection == "fused" else project_splats
        proj, opacities = project_for_render(project, splats, camera, self.antialiased, self.filter_2d)
        color, alpha, depth, stats = _RasterizeFunction.apply(
            proj.means2d.contiguous(),
            proj.conics.contiguous(),
            opacities.contiguous(),
            splats.colors.contiguous(),  # [N, C]
            proj.depths.contiguous(),  # [N] sort key and depth feature (differentiable)
            proj.radii.to(torch.int32).contiguous(),
            proj.visible.contiguous(),
            background.contiguous(),
            W,
            H,
            self.cull,
            self.count_pairs,
            self.first_window,
        )
        self._stats = stats
        return RenderOutput(color=color, alpha=alpha, depth=depth, means2d=proj.means2d, radii=proj.radii)

    def __repr__(self) -> str:
        aa = ", antialiased=True" if self.antialiased else ""
        if self.surfels:
            return "CpuRasterizer(surfels=True)"
        return f"CpuRasterizer(cull={self.cull}, projection={self.projection!r}{aa})"
