"""Strategy interface."""

from __future__ import annotations

import torch

from src.core.splats import RenderOutput
from src.data.base import View
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer


class Strategy:
    """Base: does nothing. Subclasses override the two hooks.

    Args:
        max_splats: hard cap on the number of splats (None = unbounded).
        extent: scene extent (passed at run time from the dataset; scales world-space thresholds).
    """

    def __init__(self, max_splats: int | None = None, extent: float = 1.0) -> None:
        self.max_splats = max_splats
        self.extent = extent

    def bind(self, scene, rasterizer) -> None:
        """Called once before training with the scene and the rasterizer."""

    def step_views(self, model: SplatModel, views: list[View], iteration: int,
                   generator: torch.Generator) -> list[View]:
        """The views (cameras and target images) iteration ``iteration`` trains on, given the sampled
        training ``views``: those views by default; LightGaussian's distillation replaces them by a
        teacher's renders of pseudo views."""
        return views

    def after_backward(self, model: SplatModel, renders: list[RenderOutput], iteration: int) -> None:
        """Accumulate statistics from the gradients of this iteration (before the optimiser step)."""

    def after_step(self, model: SplatModel, optimizer: SplatOptimizer, iteration: int,
                   generator: torch.Generator) -> dict:
        """Change the splat set after the optimiser step; returns counts for logging."""
        return {}

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class NoDensification(Strategy):
    """A fixed splat set (the cap is still enforced at initialisation by the model builder)."""
