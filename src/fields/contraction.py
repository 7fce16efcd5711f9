"""Coordinate contractions: unbounded scene coordinates -> the fields' bounded domain.

SplatFields reads its tri-planes at the splat centres with ``grid_sample(align_corners=False)`` and zero
padding, i.e. on [-1, 1]^3 (``src.fields.backbones``): a centre outside reads zero features (one constant
feature for every such splat) and its positional encoding sees unbounded inputs. Scenes normalised from
camera centres (``dataset=colmap``: the cameras in the unit ball, ``src.data.normalise.camera_sphere``)
have background splats far outside. A contraction maps every point of R^3 into the bounded domain first.

``mip360``, the contraction of Mip-NeRF 360 (Barron et al. 2022, eq. 10) on coordinates scaled by the radius
r (``radius``, normalised scene units) and halved so that the result lies in the unit ball, inside [-1, 1]^3:

    y = x / r
    c(y) = y                              if |y| <= 1
         = (2 - 1 / |y|) · y / |y|        otherwise      (|c(y)| < 2)
    contract(x) = c(y) / 2                               (|contract(x)| < 1)

So within radius r the map is the identity up to the scale 1 / (2r) (that ball fills |u| <= 1/2 of each
plane), and the space beyond it is folded into the shell 1/2 <= |u| < 1: distance d >= r lands at radius
1 - r / (2d). It is continuous and C1 at |x| = r (the radial profile's slope is 1 / (2r) on both sides)
and strictly increasing in |x| (along each ray, d |contract| / d|x| = r / (2 |x|^2) > 0 outside). On an
R x R plane a coordinate beyond the outermost texel centre, 1 - 1 / R (d > R r / 2 along an axis), has
a bilinear read that mixes in the zero padding, with a weight growing to 1/2 as d -> infinity. ``none`` is
the identity: the same tensor is returned, so existing runs are unchanged bit for bit.

Computed as x · s(max(|y|, 1)) / (2r) with s(n) = 2 / n - 1 / n^2: s(1) = 1 exactly, so points inside the
ball are only scaled, and the clamp keeps the origin free of 0 / 0 (finite gradients everywhere).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

CONTRACTIONS = ("none", "mip360")


def contract_mip360(x: Tensor, radius: float = 1.0) -> Tensor:
    """Mip-NeRF 360's contraction of points ``x`` [..., 3] scaled by 1 / ``radius`` and halved (module
    docstring): [..., 3] inside the open unit ball; the identity times 1 / (2 radius) within ``radius``."""
    if not radius > 0:
        raise ValueError(f"contraction radius must be > 0, got {radius}")
    y = x / radius  # [..., 3]
    n = torch.sqrt((y * y).sum(dim=-1, keepdim=True).clamp_min(1.0))  # [..., 1] max(|y|, 1)
    return y * ((2.0 / n - 1.0 / (n * n)) * 0.5)  # [..., 3]


class Contraction(nn.Module):
    """A point contraction as a module (no parameters): ``forward(x)`` [..., 3] -> [..., 3].

    Args:
        kind: ``none`` (identity: the input tensor itself) or ``mip360`` (module docstring).
        radius: for ``mip360``, the radius r (normalised scene units) inside which the map is the identity
            up to the scale 1 / (2r); 1 = the camera sphere of ``dataset=colmap``.
    """

    def __init__(self, kind: str = "none", radius: float = 1.0) -> None:
        super().__init__()
        if kind not in CONTRACTIONS:
            raise ValueError(f"contraction={kind!r}: expected one of {', '.join(CONTRACTIONS)}")
        if not radius > 0:
            raise ValueError(f"contraction_radius must be > 0, got {radius}")
        self.kind = kind
        self.radius = float(radius)

    @property
    def is_identity(self) -> bool:
        """True for ``none``."""
        return self.kind == "none"

    def forward(self, x: Tensor) -> Tensor:
        """Contracted points [..., 3] of ``x`` [..., 3] (``x`` itself for ``none``)."""
        if self.kind == "none":
            return x
        return contract_mip360(x, self.radius)

    def extra_repr(self) -> str:
        return f"kind={self.kind!r}" + (f", radius={self.radius}" if self.kind != "none" else "")
