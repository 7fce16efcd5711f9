"""Bilinear reads of the tri-planes at the query points, as a compiled kernel (``csrc/triplane_sample.cpp``).

``sample_planes(planes, uv)`` returns the features [N, P·C] of P planes [P, C, R, R] read at P point sets
uv [P, N, 2] (u indexes a plane's width, v its height, both in [-1, 1]): ``torch.nn.functional.grid_sample``
with bilinear weights, zero padding and ``align_corners=False``, laid out plane-major per point as the field
heads read it. The kernel lays the planes out channels-last so that each corner of a read is C contiguous
floats, and its backward adds into per-thread copies of the planes' gradient (grid_sample's CPU backward
scatters one channel at a time). It runs where it applies (CPU, float32, points without gradient: the query
points are buffers; eager mode); elsewhere, and with ``fast=False``, the reference is ``grid_sample`` itself.
``tests/test_triplane_sample.py`` checks that both agree, values and gradients.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from src.kernels.build import field_op_ready


def sampler_ready() -> bool:
    """True when the sampler's extension is built and loaded (a failed build warns once: torch's path then)."""
    return field_op_ready("triplane_sample")


class _Sample(torch.autograd.Function):
    """Features [N, P·C] of planes [P, C, R, R] at uv [P, N, 2]; gradient to the planes only."""

    @staticmethod
    def forward(ctx, planes: Tensor, uv: Tensor) -> Tensor:
        ctx.save_for_backward(uv)
        ctx.resolution = int(planes.shape[-1])
        return torch.ops.splatfields_cpu.triplane_sample_forward(planes.detach().contiguous(), uv.contiguous())

    @staticmethod
    def backward(ctx, g: Tensor):
        (uv,) = ctx.saved_tensors
        g_planes = torch.ops.splatfields_cpu.triplane_sample_backward(g.float().contiguous(), uv.contiguous(),
                                                                      ctx.resolution)
        return g_planes, None


def sample_planes(planes: Tensor, uv: Tensor, fast: bool = True) -> Tensor:
    """Bilinear features [N, P·C] of ``planes`` [P, C, R, R] at ``uv`` [P, N, 2] (module docstring).

    Args:
        planes: the tri-planes, one [C, R, R] image per plane.
        uv: per plane, N points (u: width, v: height) in [-1, 1]; outside reads zero.
        fast: the compiled kernel where it applies (CPU, float32 planes and points, points without
            gradient, extension built, not under ``torch.compile``, which traces ``grid_sample``);
            False: ``grid_sample``.
    """
    n = uv.shape[1]
    if (fast and planes.device.type == "cpu" and planes.dtype == torch.float32 and uv.dtype == torch.float32
            and not uv.requires_grad and planes.shape[-1] == planes.shape[-2] and not torch.compiler.is_compiling()
            and sampler_ready()):
        return _Sample.apply(planes, uv)
    feats = F.grid_sample(planes, uv[:, None], mode="bilinear", padding_mode="zeros", align_corners=False)
    return feats[:, :, 0].permute(2, 0, 1).reshape(n, -1)  # [N, P·C]
