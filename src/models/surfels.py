"""The 2D Gaussian Splatting baseline (Huang et al., SIGGRAPH 2024): free 2D Gaussian surfels.

The 3DGS model's free parameters with two tangent log-scales instead of three: a surfel is the planar
Gaussian disk spanned by the first two rotated axes of its (w, x, y, z) quaternion, scaled by (s_u, s_v);
its normal is the third rotated axis (Sec. 3). The rasterizer renders it by ray-splat intersection
(``rasterizer.surfels=true``, :mod:`src.rasterizer.surfel_ref`). Densification is 3DGS's; a split
samples its children in the surfel's plane (the reference code's zero standard deviation along the
normal).

Conventions: log-scales [N, 2], logit opacities, wxyz quaternions, SH colour coefficients.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.core.cameras import Camera
from src.core.splats import Splats
from src.models.gaussians import GaussianSplatModel


class SurfelSplatModel(GaussianSplatModel):
    """2DGS surfels: means, log-scales [N, 2] (s_u, s_v), wxyz quaternions, logit-opacities, SH coefficients.

    ``splats`` and ``bake`` return scales [N, 3] whose third column is 0 (a flat splat: the surfel
    rasterizer reads the first two; a 3DGS viewer of the baked PLY sees a flat disk).

    Args:
        init: [N, 3] initial centres (normalised world coordinates).
        random_rotations: initial quaternions uniform in [0, 1)^4 (then normalised), as the 2DGS reference
            initialises them (``torch.rand``); False: identity, as 3DGS.
        **kwargs: the arguments of :class:`GaussianSplatModel`.
    """

    def __init__(self, init: Tensor, random_rotations: bool = True, **kwargs: object) -> None:
        super().__init__(init, **kwargs)
        self.params["scales"] = nn.Parameter(self.params["scales"].data[:, :2].clone())  # [N, 2] log (s_u, s_v)
        if random_rotations:
            self.params["quats"] = nn.Parameter(torch.rand(init.shape[0], 4))

    def _scales3(self, log_scales: Tensor) -> Tensor:
        """[N, 3] linear scales (s_u, s_v, 0) of log-scales [N, 2]."""
        return F.pad(torch.exp(log_scales), (0, 1))

    def splats(self, camera: Camera) -> Splats:
        p = self.params
        return Splats(means=p["means"], scales=self._scales3(p["scales"]), quats=p["quats"],
                      opacities=torch.sigmoid(p["opacities"]), colors=self.colors(camera))

    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """Activated surfels with DC colours and scales (s_u, s_v, 0)."""
        base = super().bake(time, frame_id)
        with torch.no_grad():
            scales = self._scales3(self.params["scales"])
        return Splats(means=base.means, scales=scales, quats=base.quats, opacities=base.opacities,
                      colors=base.colors)


__all__ = ["SurfelSplatModel"]
