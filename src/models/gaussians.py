"""The 3DGS baseline: free per-splat parameters (Kerbl et al. 2023)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.core.cameras import Camera
from src.core.splats import Splats
from src.fields.flows import quat_to_rotmat_wxyz
from src.models.free import FreeSplatModel, logit
from src.models.knn import knn_base_scale
from src.models.sh import eval_sh, rgb_to_sh0
from src.optim.adam import SplatOptimizer


class GaussianSplatModel(FreeSplatModel):
    """Free splats: means, log-scales, wxyz quaternions, logit-opacities, SH colour coefficients.

    Args:
        init: [N, 3] initial centres (normalised world coordinates).
        sh_degree: maximum SH degree (0 = view-independent RGB).
        sh_degree_interval: raise the active degree every this many iterations (3DGS: 1000).
        init_opacity: initial opacity (3DGS: 0.1).
        init_color: initial RGB of every splat.
        init_scale_mult: multiplier on the kNN base scale.
        method: label of the method in run records.
    """

    def __init__(self, init: Tensor, sh_degree: int = 3, sh_degree_interval: int = 1000,
                 init_opacity: float = 0.1, init_color: float = 0.5, init_scale_mult: float = 1.0,
                 method: str = "gs3d", **_: object) -> None:
        super().__init__()
        n = init.shape[0]
        self.method = method
        self.max_sh_degree = sh_degree
        self.sh_degree_interval = sh_degree_interval
        self.active_sh_degree = 0
        scales = torch.log(knn_base_scale(init) * init_scale_mult)[:, None].repeat(1, 3)
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        k = (sh_degree + 1) ** 2
        self.params = nn.ParameterDict({
            "means": nn.Parameter(init.float().clone()),
            "scales": nn.Parameter(scales.float()),
            "quats": nn.Parameter(quats),
            "opacities": nn.Parameter(torch.full((n,), logit(init_opacity))),
            "sh0": nn.Parameter(rgb_to_sh0(torch.full((n, 1, 3), float(init_color)))),
            "shN": nn.Parameter(torch.zeros(n, k - 1, 3)),
        })

    def colors(self, camera: Camera | None, means: Tensor | None = None) -> Tensor:
        """[N, 3] colours seen from ``camera`` (SH at the active degree; DC only if camera is None).

        ``means`` (default: the splat means) are the positions the view directions are taken from.
        """
        coeffs = torch.cat([self.params["sh0"], self.params["shN"]], dim=1)
        if camera is None or self.active_sh_degree == 0:
            return torch.clamp_min(eval_sh(0, coeffs, coeffs[:, 0]) + 0.5, 0.0)
        means = self.params["means"] if means is None else means
        dirs = means - camera.center.to(means)
        dirs = F.normalize(dirs, dim=-1)
        return torch.clamp_min(eval_sh(self.active_sh_degree, coeffs, dirs) + 0.5, 0.0)

    def splats(self, camera: Camera) -> Splats:
        p = self.params
        return Splats(means=p["means"], scales=torch.exp(p["scales"]), quats=p["quats"],
                      opacities=torch.sigmoid(p["opacities"]), colors=self.colors(camera))

    def bake(self, time: float = 0.0, frame_id: int = 0) -> Splats:
        """Activated splats with DC colours (view dependence dropped only if sh_degree > 0)."""
        with torch.no_grad():
            p = self.params
            return Splats(means=p["means"].clone(), scales=torch.exp(p["scales"]),
                          quats=F.normalize(p["quats"], dim=-1), opacities=torch.sigmoid(p["opacities"]),
                          colors=self.colors(None))

    # -- densification ---------------------------------------------------------------------
    def _split_children(self, idx: Tensor, n_split: int, generator: torch.Generator) -> dict[str, Tensor]:
        """3DGS split: ``n_split`` children of each splat in ``idx``, sampled from its Gaussian, their scales
        divided by 0.8 n_split."""
        p = {k: v.data for k, v in self.params.items()}
        s = torch.exp(p["scales"][idx]).repeat(n_split, 1)
        q = p["quats"][idx].repeat(n_split, 1)  # [M, 4] wxyz, normalised by quat_to_rotmat_wxyz
        samples = torch.randn(s.shape, generator=generator).to(s) * s
        samples = F.pad(samples, (0, 3 - samples.shape[1]))  # [M, 3]; 2D surfels (two scales) sample in-plane
        rot = quat_to_rotmat_wxyz(q)  # [M, 3, 3]
        children = {k: v[idx].repeat(n_split, *([1] * (v.ndim - 1))) for k, v in p.items()}
        children["means"] = torch.einsum("nij,nj->ni", rot, samples) + p["means"][idx].repeat(n_split, 1)
        children["scales"] = torch.log(s / (0.8 * n_split))
        return children

    def _mcmc_opacity(self, targets: Tensor) -> Tensor:
        """Logit opacities shared by a target and its k copies: 1 - (1 - o)^(1 / (k + 1)) (3DGS-MCMC)."""
        counts = torch.bincount(targets, minlength=self.n_splats)[targets].to(self.params["opacities"])
        o = torch.sigmoid(self.params["opacities"].data[targets])
        o_new = (1 - (1 - o).pow(1 / (counts + 1))).clamp(1e-4, 1 - 1e-4)
        return torch.log(o_new) - torch.log1p(-o_new)

    def _zero_moments(self, optimizer: SplatOptimizer | None, rows: Tensor) -> None:
        if optimizer is None:
            return
        for p in self.params.values():
            st = optimizer.optimizer.state.get(p)
            if st:
                st["exp_avg"][rows] = 0
                st["exp_avg_sq"][rows] = 0

    @torch.no_grad()
    def relocate(self, optimizer: SplatOptimizer | None, dead: Tensor, targets: Tensor,
                 generator: torch.Generator) -> None:
        """Copy the targets' parameters onto the dead splats; targets and copies share the opacity."""
        new_logit = self._mcmc_opacity(targets)
        for p in self.params.values():
            p.data[dead] = p.data[targets]
        self.params["opacities"].data[targets] = new_logit
        self.params["opacities"].data[dead] = new_logit
        self._zero_moments(optimizer, torch.cat([dead, targets]))

    @torch.no_grad()
    def add_from(self, optimizer: SplatOptimizer | None, targets: Tensor, generator: torch.Generator) -> None:
        """Append copies of the targets; targets and copies share the MCMC-corrected opacity."""
        new_logit = self._mcmc_opacity(targets)
        self.params["opacities"].data[targets] = new_logit
        new = {k: v.data[targets].clone() for k, v in self.params.items()}
        self._edit(optimizer, None, new)
        self._zero_moments(optimizer, targets)
