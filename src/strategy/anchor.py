"""Anchor growing and pruning (Scaffold-GS, Lu et al., CVPR 2024, Sec. 3.3) as a strategy object.

For a model with the anchor interface of :class:`src.models.base.SplatModel` (each anchor decodes k
children). Statistics, from iteration ``stat_from`` to ``stop_iter``:

* per child: the norm of dL/d(means2d) in NDC units (pixels x (W/2, H/2), as the 3DGS CUDA backward
  reports it) summed over the renders in which it was drawn (radius > 0), and that count;
* per anchor: the sum of its children's opacities (negative ones as 0) over the renders that decoded
  it, and that count.

Every ``every`` iterations from ``start_iter`` to ``stop_iter``, children drawn in more than
``every x success_threshold / 2`` renders take part in growing, on ``levels`` voxel grids of edge
voxel x init_factor / level_factor^i with thresholds grad_threshold x (level_factor / 2)^i
(i = 0, 1, ...): a candidate (mean gradient >= threshold, kept with probability 1 - 0.5^(i+1)) adds an
anchor at the centre of its voxel if no anchor occupies that voxel yet; the new anchor takes the
channel-wise largest feature of the candidates in its voxel. Then anchors decoded in more than
``every x success_threshold`` renders whose mean summed opacity is below ``min_opacity`` are pruned,
and the statistics of the children and anchors that were judged start again.
"""

from __future__ import annotations

import torch
from torch import Tensor

from src.core.splats import RenderOutput
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.strategy.base import Strategy


def rows_in(rows: Tensor, table: Tensor) -> Tensor:
    """[R] bool: whether each row of ``rows`` [R, 3] (integers) occurs among the rows of ``table`` [T, 3]."""
    if rows.shape[0] == 0 or table.shape[0] == 0:
        return torch.zeros(rows.shape[0], dtype=torch.bool, device=rows.device)
    _, inverse = torch.unique(torch.cat([table, rows]), dim=0, return_inverse=True)
    present = torch.zeros(int(inverse.max()) + 1, dtype=torch.bool, device=rows.device)
    present[inverse[: table.shape[0]]] = True
    return present[inverse[table.shape[0]:]]


class AnchorStrategy(Strategy):
    """Scaffold-GS's anchor growing and pruning; thresholds from its reference code.

    Args:
        grad_threshold: mean view-space gradient a child needs to grow an anchor at level 0 (2e-4).
        stat_from / start_iter / stop_iter / every: statistics from ``stat_from``; growing and pruning
            every ``every`` iterations after ``start_iter`` and before ``stop_iter`` (1-based counts,
            as the reference's 500 / 1 500 / 15 000 / 100 of 30 000).
        min_opacity: prune anchors whose children's summed opacity per render is below this (0.005).
        success_threshold: fraction of the ``every`` iterations in which an anchor must have been decoded
            to be judged (children: half of it) (0.8).
        levels: voxel grids tried for growing (3).
        init_factor: the coarsest grid's voxel in units of the model's voxel (reference NeRF-synthetic: 4).
        level_factor: each level's voxel is this much finer, its threshold this / 2 times higher (4).
        max_splats: hard cap on the number of anchors (``model.n_splats``); growth beyond it keeps the
            candidate voxels of highest gradient.
        extent: scene extent (unused: the thresholds are in screen space and voxel units).
    """

    def __init__(self, grad_threshold: float = 2e-4, stat_from: int = 500, start_iter: int = 1500,
                 stop_iter: int = 15_000, every: int = 100, min_opacity: float = 0.005,
                 success_threshold: float = 0.8, levels: int = 3, init_factor: float = 4.0,
                 level_factor: float = 4.0, max_splats: int | None = None, extent: float = 1.0) -> None:
        super().__init__(max_splats, extent)
        if every < 1 or levels < 1 or init_factor <= 0 or level_factor <= 0:
            raise ValueError(f"strategy: every, levels, init_factor and level_factor must be positive, got "
                             f"{every}, {levels}, {init_factor}, {level_factor}")
        self.grad_threshold = grad_threshold
        self.stat_from, self.start_iter, self.stop_iter, self.every = stat_from, start_iter, stop_iter, every
        self.min_opacity = min_opacity
        self.success_threshold = success_threshold
        self.levels = levels
        self.init_factor = init_factor
        self.level_factor = level_factor
        self.grad_accum: Tensor | None = None  # [A * k] summed NDC gradient norms per child
        self.grad_count: Tensor | None = None  # [A * k] renders that drew the child
        self.opacity_accum: Tensor | None = None  # [A] summed child opacities per anchor
        self.visits: Tensor | None = None  # [A] renders that decoded the anchor

    # -- statistics ------------------------------------------------------------------------
    def _ensure(self, model: SplatModel, device: torch.device) -> None:
        """Zero statistics for the model's anchors when missing, of another size or on another device."""
        a, k = model.n_splats, model.children_per_anchor
        if self.visits is None or self.visits.shape[0] != a or self.grad_accum.shape[0] != a * k:
            self.grad_accum = torch.zeros(a * k, device=device)
            self.grad_count = torch.zeros(a * k, device=device)
            self.opacity_accum = torch.zeros(a, device=device)
            self.visits = torch.zeros(a, device=device)
        elif self.visits.device != device:  # restored from a checkpoint, which is read onto the CPU
            self.grad_accum, self.grad_count = self.grad_accum.to(device), self.grad_count.to(device)
            self.opacity_accum, self.visits = self.opacity_accum.to(device), self.visits.to(device)

    def after_backward(self, model: SplatModel, renders: list[RenderOutput], iteration: int) -> None:
        it = iteration + 1  # the reference counts iterations from 1
        if not self.stat_from < it < self.stop_iter:
            return
        for r, d in zip(renders, model.anchor_decodes(), strict=False):  # extra decodes: e.g. virtual views
            g = r.means2d.grad
            if g is None or g.shape[0] != d.children.shape[0]:
                continue
            self._ensure(model, g.device)
            self.opacity_accum[d.anchors] += d.opacity.clamp_min(0).sum(dim=1).to(self.opacity_accum)
            self.visits[d.anchors] += 1
            h, w = r.alpha.shape
            ndc = g.detach() * torch.tensor([0.5 * w, 0.5 * h], device=g.device, dtype=g.dtype)  # [M, 2]
            drawn = r.radii > 0
            self.grad_accum[d.children[drawn]] += ndc[drawn].norm(dim=-1).to(self.grad_accum)
            self.grad_count[d.children[drawn]] += 1

    # -- growing and pruning ---------------------------------------------------------------
    def after_step(self, model: SplatModel, optimizer: SplatOptimizer, iteration: int,
                   generator: torch.Generator) -> dict:
        it = iteration + 1
        if it >= self.stop_iter:
            self.grad_accum = self.grad_count = self.opacity_accum = self.visits = None
            return {}
        if it <= self.start_iter or it % self.every != 0 or self.visits is None:
            return {}
        self._ensure(model, self.visits.device)
        grown = self._grow_and_reset(model, optimizer, generator)
        pruned = self._prune(model, optimizer)
        return {"grow": grown, "prune": pruned, "n_splats": model.n_splats}

    def _grow_and_reset(self, model: SplatModel, optimizer: SplatOptimizer, generator: torch.Generator) -> int:
        """Grow anchors from the judged children, then restart those children's statistics; returns the count."""
        k, n_before = model.children_per_anchor, model.n_splats
        grads = self.grad_accum / self.grad_count.clamp_min(1)  # [A * k]
        judged = self.grad_count > self.every * self.success_threshold * 0.5  # [A * k]
        self.grow(model, optimizer, grads, judged, generator)
        n_new = model.n_splats - n_before
        self.grad_accum[judged] = 0
        self.grad_count[judged] = 0
        pad = torch.zeros(n_new * k, device=grads.device)
        self.grad_accum, self.grad_count = torch.cat([self.grad_accum, pad]), torch.cat([self.grad_count, pad])
        pad = torch.zeros(n_new, device=grads.device)
        self.opacity_accum, self.visits = torch.cat([self.opacity_accum, pad]), torch.cat([self.visits, pad])
        return n_new

    def grow(self, model: SplatModel, optimizer: SplatOptimizer, grads: Tensor, judged: Tensor,
             generator: torch.Generator) -> None:
        """Add anchors at unoccupied voxel centres of the children in ``judged`` [A * k] whose mean
        gradient ``grads`` [A * k] passes each level's threshold."""
        k = model.children_per_anchor
        children = model.child_means().reshape(-1, 3)  # [A * k, 3]
        for level in range(self.levels):
            threshold = self.grad_threshold * (self.level_factor / 2) ** level
            chance = torch.rand(grads.shape[0], generator=generator).to(grads.device)  # [A * k]
            candidates = torch.nonzero((grads >= threshold) & judged & (chance > 0.5 ** (level + 1))).squeeze(1)
            if candidates.numel() == 0:
                continue
            size = model.anchor_voxel_size() * self.init_factor / self.level_factor ** level
            cells = torch.round(children[candidates] / size).long()  # [C, 3]
            unique, slot = torch.unique(cells, dim=0, return_inverse=True)  # [U, 3], [C]
            occupied = torch.round(model.anchor_means() / size).long()  # [A', 3]
            free = ~rows_in(unique, occupied)  # [U]
            free &= self._room(model, unique.shape[0], slot, grads[candidates], free)
            if not free.any():
                continue
            new_index = torch.cumsum(free.long(), 0) - 1  # [U] index among the new anchors
            take = free[slot]  # [C] candidates in a free voxel
            model.grow_anchors(optimizer, unique[free].to(children.dtype) * size, size,
                               candidates[take] // k, new_index[slot[take]])

    def _room(self, model: SplatModel, n_cells: int, slot: Tensor, grads: Tensor, free: Tensor) -> Tensor:
        """[U] bool: the free voxels that fit under ``max_splats`` (those of highest candidate gradient)."""
        keep = torch.ones(n_cells, dtype=torch.bool, device=free.device)
        if self.max_splats is None:
            return keep
        room = max(self.max_splats - model.n_splats, 0)
        if int(free.sum()) <= room:
            return keep
        best = torch.zeros(n_cells, device=grads.device).scatter_reduce(0, slot, grads, reduce="amax")  # [U]
        best[~free] = -1.0
        keep[:] = False
        keep[torch.argsort(best, descending=True, stable=True)[:room]] = True
        return keep

    def _prune(self, model: SplatModel, optimizer: SplatOptimizer) -> int:
        """Prune judged anchors of low opacity, restart the judged anchors' statistics; returns the count."""
        judged = self.visits > self.every * self.success_threshold  # [A]
        prune = (self.opacity_accum < self.min_opacity * self.visits) & judged
        self.opacity_accum[judged] = 0
        self.visits[judged] = 0
        n_prune = int(prune.sum())
        if n_prune == 0 or n_prune >= model.n_splats:  # never the whole set
            return 0
        k = model.children_per_anchor
        keep = ~prune
        self.opacity_accum, self.visits = self.opacity_accum[keep], self.visits[keep]
        child_keep = keep.repeat_interleave(k)  # [A * k]
        self.grad_accum, self.grad_count = self.grad_accum[child_keep], self.grad_count[child_keep]
        model.prune_anchors(optimizer, prune)
        return n_prune

    def state_dict(self) -> dict:
        return {"grad_accum": self.grad_accum, "grad_count": self.grad_count, "opacity_accum": self.opacity_accum,
                "visits": self.visits}

    def load_state_dict(self, state: dict) -> None:
        self.grad_accum, self.grad_count = state.get("grad_accum"), state.get("grad_count")
        self.opacity_accum, self.visits = state.get("opacity_accum"), state.get("visits")
