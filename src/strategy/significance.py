"""Per-splat significance: how much each splat contributes to the rendered training views.

The blending weight w_ip = alpha_ip T_ip of splat i at pixel p is what LightGaussian's "global
significance" sums over all training pixels. Any differentiable rasterizer gives it without a special
kernel: render a single constant channel c_i = 1 and back-propagate the image sum; then
d(sum_p C_p) / d c_i = sum_p w_ip.
"""

from __future__ import annotations

import torch
from torch import Tensor

from src.core.splats import Splats
from src.data.base import View
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer


def splat_contributions(model: SplatModel, rasterizer: Rasterizer, views: list[View]) -> Tensor:
    """[N] sum over ``views`` and their pixels of each splat's blending weight alpha * T."""
    total = None
    for v in views:
        with torch.no_grad():
            s = model.splats(v.camera)
        ones = torch.ones(s.n, 1, dtype=s.means.dtype, device=s.means.device, requires_grad=True)
        probe = Splats(means=s.means, scales=s.scales, quats=s.quats, opacities=s.opacities, colors=ones)
        out = rasterizer.render(probe, v.camera, torch.zeros(1, dtype=s.means.dtype, device=s.means.device))
        (g,) = torch.autograd.grad(out.color.sum(), ones)
        total = g[:, 0] if total is None else total + g[:, 0]
    return total if total is not None else torch.zeros(model.n_splats)


def significance(model: SplatModel, rasterizer: Rasterizer, views: list[View], volume_power: float = 0.1) -> Tensor:
    """LightGaussian global significance: contribution x (normalised volume)^volume_power, [N]."""
    contrib = splat_contributions(model, rasterizer, views)
    with torch.no_grad():
        s = model.splats(views[0].camera).scales
        vol = s.prod(dim=-1)
        vol = vol / vol.max().clamp_min(1e-30)
    return contrib * vol.pow(volume_power)
