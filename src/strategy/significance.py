"""Per-splat significance: how much each splat contributes to the rendered training views.

The blending weight w_ip = alpha_ip T_ip of splat i at pixel p is what LightGaussian's "global
significance" sums over all training pixels. Any differentiable rasterizer gives it without a special
kernel: render a single constant channel c_i = 1 and back-propagate the image sum; then
d(sum_p C_p) / d c_i = sum_p w_ip.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats
from src.data.base import View
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer


def splat_contributions(model: SplatModel, rasterizer: Rasterizer, views: list[View]) -> Tensor:
    """[N] sum over ``views`` and their pixels of each splat's blending weight alpha * T."""
    return _contributions(lambda cam: model.splats(cam), rasterizer, views, model.n_splats)


def _contributions(splats_for: Callable[[Camera], Splats], rasterizer: Rasterizer, views: list[View],
                   n: int) -> Tensor:
    total = None
    for v in views:
        with torch.no_grad():
            s = splats_for(v.camera)
        ones = torch.ones(s.n, 1, dtype=s.means.dtype, device=s.means.device, requires_grad=True)
        probe = Splats(means=s.means, scales=s.scales, quats=s.quats, opacities=s.opacities, colors=ones)
        out = rasterizer.render(probe, v.camera, torch.zeros(1, dtype=s.means.dtype, device=s.means.device))
        (g,) = torch.autograd.grad(out.color.sum(), ones)
        total = g[:, 0] if total is None else total + g[:, 0]
    return total if total is not None else torch.zeros(n)


def _volume_term(scales: Tensor, volume_power: float) -> Tensor:
    vol = scales.prod(dim=-1)  # [N] (activated scales)
    return (vol / vol.max().clamp_min(1e-30)).pow(volume_power)


def significance(model: SplatModel, rasterizer: Rasterizer, views: list[View], volume_power: float = 0.1) -> Tensor:
    """LightGaussian global significance: contribution x (normalised volume)^volume_power, [N]."""
    contrib = splat_contributions(model, rasterizer, views)
    with torch.no_grad():
        return contrib * _volume_term(model.splats(views[0].camera).scales, volume_power)


def splat_set_significance(splats: Splats, rasterizer: Rasterizer, views: list[View],
                           volume_power: float = 0.1) -> Tensor:
    """LightGaussian global significance [N] of a fixed (e.g. baked) splat set over ``views``."""
    contrib = _contributions(lambda cam: splats, rasterizer, views, splats.n)
    return contrib * _volume_term(splats.scales, volume_power)
