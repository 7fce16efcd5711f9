"""Opacity decay of Binocular3DGS (Han, Zhou and Liu, "Binocular-Guided 3D Gaussian Splatting with View
Consistency for Sparse View Synthesis", NeurIPS 2024; its "opacity decay" strategy).

After every training step every stored opacity is multiplied by a factor just below one (0.995):
splats whose opacity the photometric gradients do not keep up fade and are then pruned by the
densification's opacity threshold, which removes floaters seen by few views. The authors' code decays
in every iteration after the densification start (``iteration > densify_from_iter``) to the end of
training, extends densification to the last iteration and turns the 3DGS opacity reset off (the decay
takes its place); those two strategy settings belong to ``+experiment=binocular3dgs``, not to this
ingredient.

The decay is applied to the stored logit opacity o as o <- logit(factor * sigmoid(o)), in place
(Adam's moments are kept, as the authors' code overwrites the parameter's data). Models that predict
opacities with a network (SplatFields) store none: the ingredient refuses them in one line.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from src.models.base import SplatModel
from src.models.gaussians import GaussianSplatModel
from src.optim.adam import SplatOptimizer
from src.sparse.base import SparseIngredient, members_of
from src.sparse.pair import MemberOptimizers
from src.utils.instantiate import ConfigError


def decayed_logits(logits: Tensor, factor: float) -> Tensor:
    """logit(factor * sigmoid(logits)) [N], computed without forming the product's logit from a rounded
    sigmoid: log(factor) + log sigmoid(o) - log(1 - factor * sigmoid(o))."""
    return math.log(factor) + torch.nn.functional.logsigmoid(logits) - torch.log1p(-factor * torch.sigmoid(logits))


class OpacityDecay(SparseIngredient):
    """Multiply every stored opacity by ``factor`` after each training step from ``start_iter`` on.

    Args:
        factor: the decay per step (Binocular3DGS: 0.995).
        start_iter: the first (1-based) iteration after which the decay applies is ``start_iter + 1``
            (the authors' code: ``iteration > densify_from_iter``, 500).
    """

    def __init__(self, factor: float = 0.995, start_iter: int = 500) -> None:
        if not 0.0 < float(factor) <= 1.0:
            raise ValueError(f"sparse.opacity_decay.factor must lie in (0, 1], got {factor}")
        self.factor = float(factor)
        self.start_iter = int(start_iter)

    def bind(self, model: SplatModel, scene, rasterizer, iterations: int) -> None:
        """Refuse, in one line, a model without stored per-splat opacities."""
        for m in members_of(model):
            if not isinstance(m, GaussianSplatModel):
                raise ConfigError(
                    f"sparse.opacity_decay: {getattr(m, 'method', '') or type(m).__name__} ({type(m).__name__}) "
                    "predicts its opacities with a network and stores none to decay; use it with a 3DGS-family "
                    "model (gs3d, mip_splatting, ...) or remove it with sparse.opacity_decay=null")

    def applies(self, iteration: int) -> bool:
        """Whether the step of 0-based ``iteration`` decays (the authors' 1-based ``iteration > start_iter``)."""
        return iteration + 1 > self.start_iter

    @torch.no_grad()
    def after_step(self, model: SplatModel, optimizer: SplatOptimizer | MemberOptimizers, iteration: int,
                   generator: torch.Generator) -> dict:
        if not self.applies(iteration) or self.factor == 1.0:
            return {}
        for m in members_of(model):
            o = m.params["opacities"]  # [N] logit opacities
            o.data.copy_(decayed_logits(o.data, self.factor))
        return {}
