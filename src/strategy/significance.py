"""Per-splat significance: how much each splat contributes to the rendered training views.

Two per-pixel contributions of splat i at pixel p can be summed over the training views:

* ``blend``: the blending weight w_ip = alpha_ip T_ip. Any differentiable rasterizer gives it without a
  special kernel: render a single constant channel c_i = 1 and back-propagate the image sum; then
  d(sum_p C_p) / d c_i = sum_p w_ip.
* ``hits``: LightGaussian's global significance (Fan et al., NeurIPS 2024, Sec. 3.2): the indicator that
  the splat takes part in pixel p's ray (the 3DGS blending rules: alpha >= 1/255 inside its tile
  rectangle, before the transmittance falls below 1e-4) times its opacity, which is what the authors'
  counting rasterizer accumulates. :func:`splat_hits` counts those pixels with the rules of
  :mod:`src.rasterizer.torch_ref`, which the compiled CPU kernel reproduces bit for bit.

Either is multiplied by the volume term (V / V_max)^beta (LightGaussian: beta = 0.1), V the product of the
three scales; the normalising constant does not change the ranking (the reference code divides by the
volume at the 90 % position of the descending order instead of the maximum).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import Splats
from src.data.base import View
from src.models.base import SplatModel
from src.rasterizer.base import Rasterizer
from src.rasterizer.projection import EPS2D, TILE, project_splats, tile_rects
from src.rasterizer.torch_ref import ALPHA_MAX, ALPHA_MIN, T_MIN

#: Per-pixel contributions :func:`global_significance` can sum.
SCORES = ("hits", "blend")


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


@torch.no_grad()
def splat_hits(splats: Splats, camera: Camera, antialiased: bool = False, filter_2d: float = 0.1) -> Tensor:
    """[N] number of pixels of ``camera`` at which each splat blends (float; 0 for culled splats).

    A splat blends at a pixel inside its 3DGS tile rectangle where its Gaussian exponent is <= 0, its
    alpha = min(0.99, opacity * exp(exponent)) is >= 1/255 and the transmittance after it stays >= 1e-4
    (front to back in a stable depth order): exactly the pairs with a non-zero blending weight in
    :class:`~src.rasterizer.torch_ref.TorchRefRasterizer`. ``antialiased`` applies Mip-Splatting's 2D
    filter (variance ``filter_2d`` px^2 and its opacity compensation) as the rasterizer option of that name.
    Conventions: OpenCV camera, wxyz quaternions, linear scales, opacities in (0, 1).
    """
    s = splats.detach()
    hits = torch.zeros(s.n, dtype=s.means.dtype, device=s.means.device)
    if s.n == 0:
        return hits
    if antialiased:
        proj = project_splats(s.means, s.quats, s.scales, camera, eps2d=filter_2d, antialiased=True)
        opac = s.opacities * proj.compensation  # [N]
    else:
        proj = project_splats(s.means, s.quats, s.scales, camera, eps2d=EPS2D)
        opac = s.opacities
    vis = torch.nonzero(proj.visible).squeeze(1)
    order = vis[torch.argsort(proj.depths[vis], stable=True)]  # [M] visible splats, front to back
    m2d, conics, op = proj.means2d[order], proj.conics[order], opac[order]
    w, h = camera.width, camera.height
    rects = tile_rects(m2d - 0.5, proj.radii[order], w, h)  # [M, 4] tile ranges (x0, y0, x1, y1)
    for ty in range(math.ceil(h / TILE)):
        y0, y1 = ty * TILE, min((ty + 1) * TILE, h)
        in_row = (rects[:, 1] <= ty) & (rects[:, 3] > ty)
        for tx in range(math.ceil(w / TILE)):
            sel = torch.nonzero(in_row & (rects[:, 0] <= tx) & (rects[:, 2] > tx)).squeeze(1)  # [S]
            if sel.numel() == 0:
                continue
            x0, x1 = tx * TILE, min((tx + 1) * TILE, w)
            ys, xs = torch.meshgrid(torch.arange(y0, y1, dtype=m2d.dtype, device=m2d.device),
                                    torch.arange(x0, x1, dtype=m2d.dtype, device=m2d.device), indexing="ij")
            pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1) + 0.5  # [P, 2] pixel centres
            dx = pix[:, None, 0] - m2d[None, sel, 0]  # [P, S]
            dy = pix[:, None, 1] - m2d[None, sel, 1]
            a, b, c = conics[sel, 0], conics[sel, 1], conics[sel, 2]
            power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
            alpha = torch.clamp(op[sel][None, :] * torch.exp(power), max=ALPHA_MAX)
            keep = (power <= 0) & (alpha >= ALPHA_MIN)
            alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
            blends = keep & (torch.cumprod(1.0 - alpha, dim=1) >= T_MIN)  # [P, S]
            hits.index_add_(0, order[sel], blends.sum(0).to(hits.dtype))
    return hits


def hit_contributions(splats_for: Callable[[Camera], Splats], rasterizer: Rasterizer, views: list[View],
                      n: int) -> Tensor:
    """[N] sum over ``views`` of each splat's pixel hits (:func:`splat_hits`) times its opacity.

    The 2D filter follows the rasterizer's ``antialiased`` / ``filter_2d`` attributes where it has them.
    """
    if getattr(rasterizer, "surfels", False):
        raise ValueError("the hits significance follows the 3DGS blending rules; with 2D surfels use score=blend")
    total = torch.zeros(n)
    aa, f2d = bool(getattr(rasterizer, "antialiased", False)), float(getattr(rasterizer, "filter_2d", 0.1))
    for v in views:
        with torch.no_grad():
            s = splats_for(v.camera)
            total = total.to(s.means) + splat_hits(s, v.camera, aa, f2d) * s.opacities.detach()
    return total


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


def global_significance(model: SplatModel, rasterizer: Rasterizer, views: list[View], volume_power: float = 0.1,
                        score: str = "hits") -> Tensor:
    """LightGaussian global significance [N] of ``model``'s splats over ``views`` (training views).

    ``score="hits"``: sum over views of pixels hit x opacity, times (V / V_max)^volume_power (the paper's
    score, Sec. 3.2); ``score="blend"``: sum of alpha T instead of hits x opacity (:func:`significance`).
    """
    if score not in SCORES:
        raise ValueError(f"significance score {score!r}: expected one of {SCORES}")
    if score == "blend":
        return significance(model, rasterizer, views, volume_power)
    contrib = hit_contributions(model.splats, rasterizer, views, model.n_splats)
    with torch.no_grad():
        return contrib * _volume_term(model.splats(views[0].camera).scales.detach(), volume_power)
