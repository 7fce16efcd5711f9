"""3DGS adaptive density control (clone / split / prune / opacity reset) as a strategy object."""

from __future__ import annotations

import torch

from src.core.splats import RenderOutput
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.strategy.base import Strategy


class ADCStrategy(Strategy):
    """Adaptive density control of 3DGS (Kerbl et al. 2023, Sec. 5), thresholds from its code.

    The view-space gradient is the norm of dL/d(means2d) converted from pixels to NDC units
    (x W/2, y H/2) as the 3DGS CUDA backward reports it, averaged over the iterations in which the
    splat was visible.

    Args:
        grad_threshold: densify splats whose mean view-space gradient exceeds this (2e-4).
        percent_dense: clone if max scale <= percent_dense * extent, else split (0.01).
        start_iter / stop_iter / every: densification window and interval (500 / 15000 / 100).
        prune_opacity: remove splats below this opacity (0.005).
        prune_big_world: after the first reset, remove splats larger than this x extent (0.1).
        reset_every: opacity reset interval (3000; 0 disables); reset_value: 0.01.
        n_split: children per split (2).
        max_splats: hard cap; when growth would exceed it, only the highest-gradient candidates grow.
        extent: scene extent (passed at run time from the dataset).
    """

    def __init__(self, grad_threshold: float = 2e-4, percent_dense: float = 0.01, start_iter: int = 500,
                 stop_iter: int = 15_000, every: int = 100, prune_opacity: float = 0.005,
                 prune_big_world: float = 0.1, reset_every: int = 3000, reset_value: float = 0.01,
                 n_split: int = 2, max_splats: int | None = None, extent: float = 1.0) -> None:
        super().__init__(max_splats, extent)
        self.grad_threshold = grad_threshold
        self.percent_dense = percent_dense
        self.start_iter, self.stop_iter, self.every = start_iter, stop_iter, every
        self.prune_opacity = prune_opacity
        self.prune_big_world = prune_big_world
        self.reset_every = reset_every
        self.reset_value = reset_value
        self.n_split = n_split
        self.grad_accum: torch.Tensor | None = None
        self.count: torch.Tensor | None = None

    def _ensure(self, n: int, device: torch.device) -> None:
        if self.grad_accum is None or self.grad_accum.shape[0] != n:
            self.grad_accum = torch.zeros(n, device=device)
            self.count = torch.zeros(n, device=device)
        elif self.grad_accum.device != device:  # restored from a checkpoint, which is read onto the CPU
            self.grad_accum, self.count = self.grad_accum.to(device), self.count.to(device)

    def after_backward(self, model: SplatModel, renders: list[RenderOutput], iteration: int) -> None:
        if iteration >= self.stop_iter:
            return
        n = model.n_splats
        for r in renders:
            g = r.means2d.grad
            if g is None or g.shape[0] != n:
                continue
            self._ensure(n, g.device)
            h, w = r.alpha.shape
            scaled = g.detach() * torch.tensor([0.5 * w, 0.5 * h], device=g.device, dtype=g.dtype)
            vis = r.radii > 0
            self.grad_accum[vis] += scaled[vis].norm(dim=-1).to(self.grad_accum.dtype)
            self.count[vis] += 1

    def after_step(self, model: SplatModel, optimizer: SplatOptimizer, iteration: int,
                   generator: torch.Generator) -> dict:
        stats: dict = {}
        it = iteration + 1  # 3DGS counts iterations from 1
        if self.start_iter < it < self.stop_iter and it % self.every == 0 and self.grad_accum is not None:
            stats.update(self._densify_and_prune(model, optimizer, it, generator))
            self.grad_accum = None
            self.count = None
        if self.reset_every > 0 and it < self.stop_iter and it % self.reset_every == 0:
            model.reset_opacity(optimizer, self.reset_value)
            stats["reset"] = 1
        return stats

    def _densify_and_prune(self, model: SplatModel, optimizer: SplatOptimizer, it: int,
                           generator: torch.Generator) -> dict:
        n = model.n_splats
        grads = self.grad_accum / self.count.clamp_min(1)
        grads[grads.isnan()] = 0.0
        big_grad = grads >= self.grad_threshold
        max_scale = model.max_scale()
        small = max_scale <= self.percent_dense * self.extent
        clone = big_grad & small
        split = big_grad & ~small
        if self.max_splats is not None:
            room = self.max_splats - n
            growth = int(clone.sum()) + int(split.sum()) * (self.n_split - 1)
            if growth > room:
                clone, split = self._cap(grads, clone, split, room)
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone or n_split:
            model.densify(optimizer, clone, split, self.n_split, generator)
        # prune (3DGS: low opacity; after the first reset, also splats too big in world space)
        op = model.opacity_values()
        prune = torch.zeros(model.n_splats, dtype=torch.bool, device=grads.device)
        if op is not None:
            prune |= op < self.prune_opacity
        if self.reset_every > 0 and it > self.reset_every:
            prune |= model.max_scale() > self.prune_big_world * self.extent
        n_prune = int(prune.sum())
        if n_prune and n_prune < model.n_splats:
            model.prune(optimizer, prune)
        return {"clone": n_clone, "split": n_split, "prune": n_prune, "n_splats": model.n_splats}

    def _cap(self, grads: torch.Tensor, clone: torch.Tensor, split: torch.Tensor,
             room: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Keep the highest-gradient candidates whose growth fits in ``room`` more splats."""
        clone_out = torch.zeros_like(clone)
        split_out = torch.zeros_like(split)
        if room <= 0:
            return clone_out, split_out
        cand = torch.nonzero(clone | split).squeeze(1)
        order = cand[torch.argsort(grads[cand], descending=True, stable=True)]
        used = 0
        for i in order.tolist():
            cost = 1 if clone[i] else self.n_split - 1
            if used + cost > room:
                break
            used += cost
            if clone[i]:
                clone_out[i] = True
            else:
                split_out[i] = True
        return clone_out, split_out

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "count": self.count}

    def load_state_dict(self, state: dict) -> None:
        self.grad_accum = state.get("grad_accum")
        self.count = state.get("count")
