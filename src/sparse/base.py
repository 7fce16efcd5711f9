"""The interface of a training-free sparse-view ingredient and the recipe that composes them.

An ingredient changes how a scene model is trained, never what it is: it acts through the hooks the
trainer calls in every step (:meth:`SparseIngredient.train_splats` between the model and the
rasterizer, :meth:`SparseIngredient.loss_terms` after the step's renders,
:meth:`SparseIngredient.after_step` after the optimiser and the densification strategy), so the same
ingredient composes with 3DGS, Mip-Splatting and SplatFields alike. Evaluation never calls a hook.

Conventions: splats are activated (opacities in (0, 1), linear scales, wxyz quaternions); models
store logit opacities and log-scales; cameras are OpenCV pinholes (x right, y down, z forward).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from src.core.splats import RenderOutput, Splats
from src.data.base import Scene, View
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.base import Rasterizer
from src.sparse.pair import CoTrainedPair, MemberOptimizers
from src.strategy.base import Strategy


class SparseIngredient:
    """One training-free sparse-view technique; every hook does nothing here."""

    def prepare(self, model: SplatModel, strategy: Strategy, build_model: Callable[[], SplatModel],
                build_strategy: Callable[[], Strategy]) -> tuple[SplatModel, Strategy]:
        """The model and strategy to train (before the optimiser is built); ``model`` and ``strategy`` here.

        ``build_model`` / ``build_strategy`` build another model / strategy of the run's configuration
        (CoR-GS trains two).
        """
        return model, strategy

    def bind(self, model: SplatModel, scene: Scene, rasterizer: Rasterizer, iterations: int) -> None:
        """Called once before training (before a checkpoint is resumed) with the run's iteration count."""

    def train_splats(self, model: SplatModel, splats: list[Splats], iteration: int,
                     generator: torch.Generator) -> list[Splats]:
        """The splats the step renders, one per camera, given the model's ``splats``; these by default."""
        return splats

    def loss_terms(self, model: SplatModel, views: list[View], renders: list[RenderOutput], rasterizer: Rasterizer,
                   background: Tensor, iteration: int, generator: torch.Generator) -> dict[str, Tensor]:
        """Weighted loss terms (scalars) added to the step's objective; none by default."""
        return {}

    def after_step(self, model: SplatModel, optimizer: SplatOptimizer | MemberOptimizers, iteration: int,
                   generator: torch.Generator) -> dict:
        """Change the model after the optimiser step and the strategy; counts for logging."""
        return {}

    def final_model(self, model: SplatModel) -> SplatModel:
        """The model that is evaluated and written after training; ``model`` by default."""
        return model


class SparseRecipe(SparseIngredient):
    """The ``sparse`` config group's object: at most one ingredient per slot, applied in slot order.

    Args:
        dropout: DropGaussian (:class:`src.sparse.dropgaussian.DropGaussian`) or None.
        opacity_decay: Binocular3DGS's opacity decay (:class:`src.sparse.opacity_decay.OpacityDecay`) or None.
        binocular: Binocular3DGS's self-consistency loss (:class:`src.sparse.binocular.BinocularConsistency`)
            or None.
        corgs: CoR-GS co-training (:class:`src.sparse.corgs.CoRGS`) or None.

    A recipe without ingredients (``sparse=none``) changes nothing (:attr:`empty`).
    """

    def __init__(self, dropout: SparseIngredient | None = None, opacity_decay: SparseIngredient | None = None,
                 binocular: SparseIngredient | None = None, corgs: SparseIngredient | None = None) -> None:
        self.slots = {"corgs": corgs, "dropout": dropout, "binocular": binocular, "opacity_decay": opacity_decay}
        self.ingredients = [i for i in self.slots.values() if i is not None]

    @property
    def empty(self) -> bool:
        return not self.ingredients

    def __repr__(self) -> str:
        names = [k for k, v in self.slots.items() if v is not None]
        return f"SparseRecipe({', '.join(names) or 'none'})"

    def prepare(self, model: SplatModel, strategy: Strategy, build_model: Callable[[], SplatModel],
                build_strategy: Callable[[], Strategy]) -> tuple[SplatModel, Strategy]:
        for ingredient in self.ingredients:
            model, strategy = ingredient.prepare(model, strategy, build_model, build_strategy)
        return model, strategy

    def bind(self, model: SplatModel, scene: Scene, rasterizer: Rasterizer, iterations: int) -> None:
        for ingredient in self.ingredients:
            ingredient.bind(model, scene, rasterizer, iterations)

    def train_splats(self, model: SplatModel, splats: list[Splats], iteration: int,
                     generator: torch.Generator) -> list[Splats]:
        for ingredient in self.ingredients:
            splats = ingredient.train_splats(model, splats, iteration, generator)
        return splats

    def loss_terms(self, model: SplatModel, views: list[View], renders: list[RenderOutput], rasterizer: Rasterizer,
                   background: Tensor, iteration: int, generator: torch.Generator) -> dict[str, Tensor]:
        terms: dict[str, Tensor] = {}
        for ingredient in self.ingredients:
            terms.update(ingredient.loss_terms(model, views, renders, rasterizer, background, iteration, generator))
        return terms

    def after_step(self, model: SplatModel, optimizer: SplatOptimizer | MemberOptimizers, iteration: int,
                   generator: torch.Generator) -> dict:
        stats: dict = {}
        for ingredient in self.ingredients:
            stats.update(ingredient.after_step(model, optimizer, iteration, generator))
        return stats

    def final_model(self, model: SplatModel) -> SplatModel:
        for ingredient in self.ingredients:
            model = ingredient.final_model(model)
        return model


def members_of(model: SplatModel) -> list[SplatModel]:
    """The models trained side by side in ``model``: the two of a :class:`CoTrainedPair`, else ``[model]``."""
    return list(model.members) if isinstance(model, CoTrainedPair) else [model]


def split_by_member(model: SplatModel, items: list) -> list[list]:
    """``items`` laid out once per member, member after member (the step's views, cameras or renders of a
    :class:`CoTrainedPair`), as one list per member; ``[items]`` for a single model."""
    k = len(members_of(model))
    if len(items) % k:
        raise ValueError(f"{len(items)} items cannot be split between {k} co-trained models")
    n = len(items) // k
    return [items[i * n:(i + 1) * n] for i in range(k)]


def optimizer_for(model: SplatModel,
                  factory: Callable[[list[dict]], SplatOptimizer]) -> SplatOptimizer | MemberOptimizers:
    """``factory(model.param_groups())``, or for a :class:`CoTrainedPair` one such optimiser per member."""
    if isinstance(model, CoTrainedPair):
        return MemberOptimizers([factory(m.param_groups()) for m in model.members])
    return factory(model.param_groups())
