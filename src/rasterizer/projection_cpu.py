"""Fused C++/OpenMP EWA projection with a hand-written backward (drop-in for :func:`project_splats`).

:func:`project_splats_fused` returns exactly what :func:`src.rasterizer.projection.project_splats`
returns: the forward repeats the torch projection's float operations one by one (bit-identical
means2d, conics, depths, radii and visible in float32 and float64), and the backward is the chain
rule of the same graph (including torch's where/clamp masks) evaluated in double, in one pass per
splat instead of ~150 small torch kernels and their autograd graph. See csrc/project_cpu.cpp.

With ``antialiased=True`` (Mip-Splatting's 2D Mip filter; ``eps2d`` is then the filter's variance)
the kernel also returns the determinant ratio det(Sigma2D) / det(Sigma2D + eps2d I) (floored at
``AA_RATIO_MIN``), whose ``torch.sqrt`` is the opacity compensation: taken by torch, so that it is
bit-identical to the torch projection's (torch's CPU sqrt is MKL's, not always correctly rounded);
the kernel's backward takes the ratio's incoming gradient.

Conventions: OpenCV camera (x right, y down, z forward; ``world_to_cam`` [4, 4]), quaternions
(w, x, y, z) normalised inside, linear scales (standard deviations), pixel centres at i + 0.5.
Differentiable in means, quats and scales; the camera is not differentiated (a camera whose
``world_to_cam`` requires grad falls back to the torch projection).

In float32 the backward's chain rule runs in double from the float32 forward intermediates, so its
gradients are slightly closer to the float64 truth than torch's float32 autograd; for splats whose
covariance overflows float32 (scales ~1e20) the two may disagree on which gradients are non-finite.

The extension is built on first use (see :mod:`src.kernels.build`).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.kernels.build import load_extension
from src.rasterizer.projection import (
    AA_RATIO_MIN,
    EPS2D,
    FRUSTUM_CLAMP,
    NEAR_PLANE,
    TILE,
    Projected,
    project_splats,
)

CamArgs = tuple[float, float, float, float, int, int, float, float, float, int]


def _camera_args(camera: Camera, eps2d: float = EPS2D) -> CamArgs:
    """(fx, fy, cx, cy, width, height, near, clamp, eps2d, tile) as passed to the C++ ops."""
    return (float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy), int(camera.width),
            int(camera.height), NEAR_PLANE, FRUSTUM_CLAMP, float(eps2d), TILE)


def _rows(g: Tensor, dt: torch.dtype) -> Tensor:
    """``g`` in dtype ``dt`` with contiguous rows; any row stride is kept (no copy of the strided
    column views the CPU rasterizer's backward hands over), anything else is made contiguous."""
    g = g.to(dt)
    if g.dim() == 2 and g.stride(1) == 1 and g.stride(0) >= 0:
        return g
    if g.dim() == 1 and g.stride(0) >= 0:
        return g
    return g.contiguous()


class _ProjectFunction(torch.autograd.Function):
    """EWA projection; differentiable in means [N, 3], quats [N, 4], scales [N, 3].

    Inputs: means, quats (wxyz), scales (linear), viewmat [4, 4] world-to-camera (all one dtype,
    float32 or float64, contiguous, CPU), cam (:data:`CamArgs`).
    Outputs: means2d [N, 2], conics [N, 3], depths [N] (differentiable), radii [N] int32,
    visible [N] bool (not differentiable).
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor, cam: CamArgs
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        means2d, conics, depths, radii, visible, finite = load_extension().project_forward(
            means, quats, scales, viewmat, *cam)
        ctx.save_for_backward(means, quats, scales, viewmat, finite)
        ctx.cam = cam
        ctx.mark_non_differentiable(radii, visible)
        return means2d, conics, depths, radii, visible

    @staticmethod
    def backward(ctx: Any, g_means2d: Tensor, g_conics: Tensor, g_depths: Tensor,  # type: ignore[override]
                 _g_radii: Tensor | None, _g_visible: Tensor | None):
        means, quats, scales, viewmat, finite = ctx.saved_tensors
        dt = means.dtype
        g_means, g_quats, g_scales = load_extension().project_backward(
            means, quats, scales, viewmat, *ctx.cam,
            _rows(g_means2d, dt),  # [N, 2]
            _rows(g_conics, dt),  # [N, 3]
            _rows(g_depths, dt),  # [N]
            finite)  # [N] bool: all forward intermediates finite (zero gradients skip the chain rule)
        return g_means, g_quats, g_scales, None, None


class _ProjectAAFunction(torch.autograd.Function):
    """The antialiased EWA projection (2D Mip filter): :class:`_ProjectFunction`'s outputs, then the
    determinant ratio clamp(det(Sigma2D) / det(Sigma2D + eps2d I), min=AA_RATIO_MIN) [N]
    (differentiable). ``cam`` carries the filter's variance as eps2d."""

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any, means: Tensor, quats: Tensor, scales: Tensor, viewmat: Tensor, cam: CamArgs
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        means2d, conics, depths, radii, visible, finite, ratio = load_extension().project_forward_aa(
            means, quats, scales, viewmat, *cam, AA_RATIO_MIN)
        ctx.save_for_backward(means, quats, scales, viewmat, finite)
        ctx.cam = cam
        ctx.mark_non_differentiable(radii, visible)
        return means2d, conics, depths, radii, visible, ratio

    @staticmethod
    def backward(ctx: Any, g_means2d: Tensor, g_conics: Tensor, g_depths: Tensor,  # type: ignore[override]
                 _g_radii: Tensor | None, _g_visible: Tensor | None, g_ratio: Tensor):
        means, quats, scales, viewmat, finite = ctx.saved_tensors
        dt = means.dtype
        g_means, g_quats, g_scales = load_extension().project_backward_aa(
            means, quats, scales, viewmat, *ctx.cam, AA_RATIO_MIN,
            _rows(g_means2d, dt),  # [N, 2]
            _rows(g_conics, dt),  # [N, 3]
            _rows(g_depths, dt),  # [N]
            _rows(g_ratio, dt),  # [N]
            finite)
        return g_means, g_quats, g_scales, None, None


def project_splats_fused(means: Tensor, quats: Tensor, scales: Tensor, camera: Camera, eps2d: float = EPS2D,
                         antialiased: bool = False) -> Projected:
    """Project 3D Gaussians into ``camera`` (3DGS EWA rules) with the compiled kernel.

    Same contract and results as :func:`src.rasterizer.projection.project_splats`.

    Args:
        means: [N, 3] world centres; quats: [N, 4] (w, x, y, z), any non-zero norm; scales: [N, 3]
            linear standard deviations. CPU, float32 or float64 (one dtype).
        camera: OpenCV pinhole camera (``world_to_cam`` is cast to the splats' dtype as the torch
            projection does).
        eps2d: variance (pixels^2) added to the 2D covariance diagonal (3DGS dilation 0.3; the 2D
            Mip filter's variance with ``antialiased``).
        antialiased: also return the opacity compensation (Mip-Splatting's 2D Mip filter).
    Returns:
        :class:`Projected`: means2d [N, 2] (pixel centres at i + 0.5), conics [N, 3], depths [N],
        radii [N] int32 (0 if culled), visible [N] bool, compensation [N] or None; differentiable
        in means, quats and scales.
    Raises:
        ValueError / TypeError: non-CPU tensors, mixed or unsupported dtypes, bad shapes.
    """
    if camera.world_to_cam.requires_grad:  # camera gradients: only the torch graph has them
        return project_splats(means, quats, scales, camera, eps2d=eps2d, antialiased=antialiased)
    dt = means.dtype
    if dt not in (torch.float32, torch.float64):
        raise TypeError(f"project_splats_fused supports float32/float64, got {dt}")
    for name, t, cols in (("means", means, 3), ("quats", quats, 4), ("scales", scales, 3)):
        if t.device.type != "cpu":
            raise ValueError(f"project_splats_fused needs CPU tensors; {name} is on {t.device}")
        if t.dtype != dt:
            raise TypeError(f"{name} is {t.dtype} but means is {dt}")
        if t.dim() != 2 or t.shape[1] != cols or t.shape[0] != means.shape[0]:
            raise ValueError(f"{name} must be [N, {cols}] with N = {means.shape[0]}, got {tuple(t.shape)}")
    viewmat = camera.world_to_cam.detach().to(device="cpu", dtype=dt).contiguous()  # [4, 4]
    args = (means.contiguous(), quats.contiguous(), scales.contiguous(), viewmat, _camera_args(camera, eps2d))
    if antialiased:
        means2d, conics, depths, radii, visible, ratio = _ProjectAAFunction.apply(*args)
        return Projected(means2d=means2d, conics=conics, depths=depths, radii=radii, visible=visible,
                         compensation=torch.sqrt(ratio))
    means2d, conics, depths, radii, visible = _ProjectFunction.apply(*args)
    return Projected(means2d=means2d, conics=conics, depths=depths, radii=radii, visible=visible)
