"""DropGaussian (Park, Ryu and Kim, "DropGaussian: Structural Regularization for Sparse-view Gaussian
Splatting", CVPR 2025).

In every training step each splat is dropped independently with probability r (its opacity set to 0)
and every kept splat's opacity is multiplied by 1 / (1 - r), so each splat's expected opacity is
unchanged (Sec. 3.2: o~_i = M(i) o_i, M(i) = 1 / (1 - r) for the kept ones). The rate grows over
training, r_t = gamma * t / t_total (progressive drop rate); the authors' code uses gamma = 0.2 over its
10 000 iterations. Evaluation renders every splat: the trainer applies the drop between the model and
the rasterizer of a training step only, and a model in eval mode is never dropped.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from src.core.splats import Splats
from src.models.base import SplatModel
from src.sparse.base import SparseIngredient


class DropGaussian(SparseIngredient):
    """Random splat dropping with opacity compensation at a rate rising linearly over training.

    Args:
        max_rate: gamma, the rate reached at the end of training (the authors' code: 0.2).
        total_iterations: t_total of the schedule; None = the run's iteration count (what the authors'
            code divides by).

    Drops are drawn with the run's ``torch.Generator`` (on the CPU, then moved to the splats' device),
    so a resumed run draws the same drops as an uninterrupted one.
    """

    def __init__(self, max_rate: float = 0.2, total_iterations: int | None = None) -> None:
        if not 0.0 <= float(max_rate) < 1.0:
            raise ValueError(f"sparse.dropout.max_rate must lie in [0, 1), got {max_rate}")
        if total_iterations is not None and int(total_iterations) <= 0:
            raise ValueError(f"sparse.dropout.total_iterations must be positive or null, got {total_iterations}")
        self.max_rate = float(max_rate)
        self.total_iterations = None if total_iterations is None else int(total_iterations)
        self._total = self.total_iterations

    def bind(self, model, scene, rasterizer, iterations: int) -> None:
        if self.total_iterations is None:
            self._total = max(1, int(iterations))

    def rate(self, iteration: int) -> float:
        """r at 0-based ``iteration``: gamma * min(1, (iteration + 1) / t_total) (the authors count from 1)."""
        if self._total is None:
            raise RuntimeError("DropGaussian.rate before bind(): the schedule's t_total is not known")
        return self.max_rate * min(1.0, max(iteration + 1, 0) / self._total)

    @staticmethod
    def compensation(rate: float) -> float:
        """The factor on a kept splat's opacity, 1 / (1 - rate): kept with probability 1 - rate, the
        expected factor is exactly 1."""
        return 1.0 / (1.0 - rate)

    @classmethod
    def drop(cls, splats: Splats, rate: float, generator: torch.Generator) -> Splats:
        """``splats`` with each splat dropped with probability ``rate`` and the kept ones' opacities
        multiplied by :meth:`compensation`; the same object when ``rate`` is 0.

        Every other attribute is the input's tensor, so the dropped splats keep their place (N is
        unchanged: densification statistics stay aligned) and receive no gradient through the render.
        """
        if rate <= 0.0 or splats.n == 0:
            return splats
        keep = torch.rand(splats.n, generator=generator) >= rate  # [N] bool, on the generator's device
        factor = keep.to(splats.opacities.dtype) * cls.compensation(rate)  # [N] 0 or 1 / (1 - r)
        return replace(splats, opacities=splats.opacities * factor.to(splats.opacities.device))

    def train_splats(self, model: SplatModel, splats: list[Splats], iteration: int,
                     generator: torch.Generator) -> list[Splats]:
        """An independent drop for each camera's splats of the step; none when ``model`` is in eval mode."""
        if not model.training:
            return splats
        r = self.rate(iteration)
        return [self.drop(s, r, generator) for s in splats]
