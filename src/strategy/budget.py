"""A fixed splat budget: relocate dead splats and grow to the cap (MCMC-style), then prune by significance.

Unlike 3DGS densification (unbounded cloning) this keeps ``max_splats`` as a budget:
* every ``every`` iterations in [start_iter, stop_iter): splats whose opacity is below ``dead_opacity``
  are moved onto live splats sampled with probability proportional to their opacity (Kheradmand et al.,
  "3DGS as MCMC"), and ``grow_fraction`` x N new splats are added the same way until the cap;
* optionally, at ``prune_at`` the least significant splats (LightGaussian global significance over the
  training views) are removed until ``prune_keep`` x N remain.
"""

from __future__ import annotations

import torch

from src.core.splats import RenderOutput
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.strategy.base import Strategy
from src.strategy.significance import significance


class BudgetStrategy(Strategy):
    """Relocation + growth to a fixed budget, with optional significance pruning.

    Args:
        max_splats: the budget (hard cap).
        start_iter, stop_iter, every: relocation window and interval.
        dead_opacity: splats below this opacity are relocated (MCMC: 0.005).
        grow_fraction: add this fraction of N per event until the cap (MCMC: 0.05).
        prune_at: iteration at which significance pruning runs (None = never).
        prune_keep: fraction of splats kept by significance pruning.
        volume_power: exponent of the volume term of the significance score (LightGaussian: 0.1).
        prune_views: training views scored for significance (None = all).
    """

    def __init__(self, max_splats: int | None = 50_000, start_iter: int = 300, stop_iter: int = 2500,
                 every: int = 100, dead_opacity: float = 0.005, grow_fraction: float = 0.05,
                 prune_at: int | None = None, prune_keep: float = 0.5, volume_power: float = 0.1,
                 prune_views: int | None = None, extent: float = 1.0) -> None:
        super().__init__(max_splats, extent)
        self.start_iter, self.stop_iter, self.every = start_iter, stop_iter, every
        self.dead_opacity = dead_opacity
        self.grow_fraction = grow_fraction
        self.prune_at = prune_at
        self.prune_keep = prune_keep
        self.volume_power = volume_power
        self.prune_views = prune_views
        self._scene = None
        self._rasterizer = None

    def bind(self, scene, rasterizer) -> None:
        """Give the strategy the training views and the rasterizer (for significance pruning)."""
        self._scene, self._rasterizer = scene, rasterizer

    def after_backward(self, model: SplatModel, renders: list[RenderOutput], iteration: int) -> None:
        return None

    def after_step(self, model: SplatModel, optimizer: SplatOptimizer, iteration: int,
                   generator: torch.Generator) -> dict:
        it = iteration + 1
        stats: dict = {}
        if self.start_iter <= it < self.stop_iter and it % self.every == 0:
            stats.update(self._relocate_and_grow(model, optimizer, generator))
        if self.prune_at is not None and it == self.prune_at and self._scene is not None:
            stats.update(self._prune(model, optimizer))
        return stats

    def _sample_targets(self, weights: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor:
        p = weights.clamp_min(0).double().cpu()
        if p.sum() <= 0:
            p = torch.ones_like(p)
        return torch.multinomial(p / p.sum(), n, replacement=True, generator=generator)

    def _relocate_and_grow(self, model: SplatModel, optimizer: SplatOptimizer, generator: torch.Generator) -> dict:
        op = model.opacity_values()
        if op is None:
            return {}
        op = op.cpu()
        dead = torch.nonzero(op < self.dead_opacity).squeeze(1)
        alive_w = torch.where(op >= self.dead_opacity, op, torch.zeros_like(op))
        n_reloc = int(dead.numel())
        if n_reloc and alive_w.sum() > 0:
            model.relocate(optimizer, dead, self._sample_targets(alive_w, n_reloc, generator), generator)
        n = model.n_splats
        cap = self.max_splats if self.max_splats is not None else n
        n_add = max(0, min(cap, int(n * (1 + self.grow_fraction))) - n)
        if n_add:
            op = model.opacity_values()
            w = op.cpu() if op is not None else torch.ones(n)
            model.add_from(optimizer, self._sample_targets(w, n_add, generator), generator)
        return {"relocated": n_reloc, "added": n_add, "n_splats": model.n_splats}

    def _prune(self, model: SplatModel, optimizer: SplatOptimizer) -> dict:
        views = self._scene.train if self.prune_views is None else self._scene.train[: self.prune_views]
        score = significance(model, self._rasterizer, views, self.volume_power).cpu()
        keep_n = max(1, round(self.prune_keep * model.n_splats))
        order = torch.argsort(score, descending=True, stable=True)
        mask = torch.ones(model.n_splats, dtype=torch.bool)
        mask[order[:keep_n]] = False
        model.prune(optimizer, mask.to(model.canonical_means().device))
        return {"pruned": int(mask.sum()), "n_splats": model.n_splats}
