"""Pure-PyTorch reference rasterizer (the oracle every faster backend is tested against).

Per 16x16 tile, it gathers the splats whose 3DGS tile rectangle covers the tile (in a stable depth
order) and composites them densely with autograd. It is slow (seconds per render at 100-200 px,
O(pairs) memory) but simple enough to check against finite differences in float64.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from src.core.cameras import Camera
from src.core.splats import RenderOutput, Splats
from src.rasterizer.base import Rasterizer, check_surfels
from src.rasterizer.projection import TILE, project_for_render, project_splats, tile_rects
from src.rasterizer.surfel_ref import render_surfels_ref

ALPHA_MAX = 0.99  # 3DGS clamps alpha to 0.99
ALPHA_MIN = 1.0 / 255.0  # 3DGS skips fragments below 1/255
T_MIN = 1e-4  # 3DGS stops before the splat that takes T below 1e-4


def composite_tile(
    pix: Tensor,  # [P, 2] pixel centres (x, y)
    means2d: Tensor,  # [M, 2] depth-sorted
    conics: Tensor,  # [M, 3]
    opacities: Tensor,  # [M]
    feats: Tensor,  # [M, C + 1] colours with depth appended
) -> tuple[Tensor, Tensor]:
    """Front-to-back alpha compositing of M depth-sorted splats over P pixels (3DGS rules).

    Returns:
        (accumulated features [P, C + 1], final transmittance [P]).
    """
    dx = pix[:, None, 0] - means2d[None, :, 0]  # [P, M]
    dy = pix[:, None, 1] - means2d[None, :, 1]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
    alpha = torch.clamp(opacities[None, :] * torch.exp(power), max=ALPHA_MAX)
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
    # termination: a splat blends only if T after it stays >= T_MIN (T is non-increasing, so a prefix)
    with torch.no_grad():
        t_incl = torch.cumprod(1.0 - alpha, dim=1)
        blend = t_incl >= T_MIN
    alpha = torch.where(blend, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    t_incl = torch.cumprod(one_minus, dim=1)
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
    weights = alpha * t_excl  # [P, M]
    return weights @ feats, t_incl[:, -1]


class TorchRefRasterizer(Rasterizer):
    """Reference rasterizer in pure PyTorch with autograd backward.

    Peak memory is O(pairs): every (pixel, splat) pair of a tile's list is materialised.

    Args:
        antialiased: Mip-Splatting's 2D Mip filter (Yu et al. 2024, Sec. 5.2) instead of 3DGS's
            dilation: Sigma2D + filter_2d I, opacities times sqrt(det(Sigma2D) / det(Sigma2D + filter_2d I)).
        filter_2d: variance (pixels^2) of the 2D Mip filter (Mip-Splatting: 0.1); unused unless
            ``antialiased`` (the dilation is then 0.3, :data:`~src.rasterizer.projection.EPS2D`).
        surfels: render the splats as 2D Gaussian surfels by ray-splat intersection (2DGS, Huang et al.
            2024; :func:`~src.rasterizer.surfel_ref.render_surfels_ref`, which returns a
            :class:`~src.core.splats.SurfelRenderOutput`); not combinable with ``antialiased``.
    """

    name = "torch_ref"

    def __init__(self, antialiased: bool = False, filter_2d: float = 0.1, surfels: bool = False) -> None:
        self.antialiased = bool(antialiased)
        self.filter_2d = float(filter_2d)
        self.surfels = check_surfels(surfels, antialiased)

    def render(self, splats: Splats, camera: Camera, background: Tensor | None = None) -> RenderOutput:
        """Render splats (see :class:`Rasterizer`). Differentiable via autograd."""
        if self.surfels:
            return render_surfels_ref(splats, camera, background)
        splats.validate()
        device, dtype = splats.means.device, splats.means.dtype
        W, H = camera.width, camera.height
        C = splats.colors.shape[1]
        if background is None:
            background = torch.zeros(C, device=device, dtype=dtype)
        background = background.to(device=device, dtype=dtype)

        proj, opacities = project_for_render(project_splats, splats, camera, self.antialiased, self.filter_2d)
        vis_idx = torch.nonzero(proj.visible).squeeze(1)
        # stable depth order of the visible splats (ties keep index order)
        order = vis_idx[torch.argsort(proj.depths.detach()[vis_idx], stable=True)]
        means2d = proj.means2d[order]
        conics = proj.conics[order]
        opac = opacities[order]
        feats = torch.cat([splats.colors[order], proj.depths[order, None]], dim=1)
        rects = tile_rects(proj.means2d.detach()[order] - 0.5, proj.radii[order], W, H)

        gx, gy = math.ceil(W / TILE), math.ceil(H / TILE)
        out_rows = []
        t_rows = []
        for ty in range(gy):
            row_feats = []
            row_t = []
            y0, y1 = ty * TILE, min((ty + 1) * TILE, H)
            in_row = (rects[:, 1] <= ty) & (rects[:, 3] > ty)
            for tx in range(gx):
                x0, x1 = tx * TILE, min((tx + 1) * TILE, W)
                ys, xs = torch.meshgrid(
                    torch.arange(y0, y1, device=device, dtype=dtype),
                    torch.arange(x0, x1, device=device, dtype=dtype),
                    indexing="ij",
                )
                pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1) + 0.5
                sel = torch.nonzero(in_row & (rects[:, 0] <= tx) & (rects[:, 2] > tx)).squeeze(1)
                if sel.numel() == 0:
                    acc = torch.zeros(pix.shape[0], C + 1, device=device, dtype=dtype)
                    tt = torch.ones(pix.shape[0], device=device, dtype=dtype)
                else:
                    acc, tt = composite_tile(pix, means2d[sel], conics[sel], opac[sel], feats[sel])
                row_feats.append(acc.reshape(y1 - y0, x1 - x0, C + 1))
                row_t.append(tt.reshape(y1 - y0, x1 - x0))
            out_rows.append(torch.cat(row_feats, dim=1))
            t_rows.append(torch.cat(row_t, dim=1))
        out = torch.cat(out_rows, dim=0)  # [H, W, C + 1]
        t_final = torch.cat(t_rows, dim=0)  # [H, W]
        color = out[..., :C] + t_final[..., None] * background
        return RenderOutput(
            color=color,
            alpha=1.0 - t_final,
            depth=out[..., C],
            means2d=proj.means2d,
            radii=proj.radii,
        )

    def __repr__(self) -> str:
        return f"TorchRefRasterizer(antialiased={self.antialiased}, surfels={self.surfels})"
