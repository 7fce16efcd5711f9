"""SuGaR's density control (Guédon and Lepetit, CVPR 2024, Sec. 4.1): 3DGS adaptive density control during the
warm-up, then one hard prune of the splats whose opacity is below a threshold once the entropy term has
pushed the opacities to 0 or 1 (:mod:`src.losses.sugar`)."""

from __future__ import annotations

import logging

import torch

from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.strategy.default import ADCStrategy
from src.utils.instantiate import ConfigError
from src.utils.validate import ConfigValueError

log = logging.getLogger(__name__)


def prune_below(model: SplatModel, optimizer: SplatOptimizer | None, threshold: float) -> int:
    """Remove every splat whose opacity is below ``threshold``; returns how many were removed.

    Nothing is removed (and 0 returned, with a warning) if no splat would be left.

    Raises:
        ConfigError: (one line) a model whose opacities are not known per splat (``opacity_values`` None).
    """
    opacities = model.opacity_values()
    if opacities is None:
        raise ConfigError(f"strategy=sugar: {getattr(model, 'method', '') or type(model).__name__} "
                          f"({type(model).__name__}) has no per-splat opacities for SuGaR's opacity prune to read; "
                          "use it with a 3DGS-family model (+experiment=sugar: gs3d's)")
    mask = opacities < threshold  # [N]
    n = int(mask.sum())
    if n == 0:
        return 0
    if n == model.n_splats:
        log.warning("SuGaR prune: every splat has opacity < %.3g; none removed", threshold)
        return 0
    model.prune(optimizer, mask)
    return n


class SugarStrategy(ADCStrategy):
    """3DGS adaptive density control (:class:`ADCStrategy`) over SuGaR's warm-up, then one opacity prune.

    Args:
        prune_at: after this many iterations (0-based iteration ``prune_at - 1``), remove the splats whose
            opacity is below ``prune_opacity_hard`` (SuGaR's code: once, after 9 000 of 15 000 iterations).
        prune_opacity_hard: the threshold of that prune (SuGaR: 0.5), in [0, 1].
        **kwargs: the arguments of :class:`ADCStrategy` (``stop_iter``: the end of the warm-up, SuGaR's 3DGS
            densifies until iteration 7 000).

    Raises:
        ConfigValueError: ``prune_opacity_hard`` outside [0, 1], naming its ``strategy.`` key.
    """

    def __init__(self, prune_at: int = 9000, prune_opacity_hard: float = 0.5, **kwargs) -> None:
        super().__init__(**kwargs)
        if not 0.0 <= prune_opacity_hard <= 1.0:
            raise ConfigValueError(f"strategy.prune_opacity_hard={prune_opacity_hard!r}: expected a value in [0, 1]")
        self.prune_at = int(prune_at)
        self.prune_opacity_hard = float(prune_opacity_hard)

    def after_step(self, model: SplatModel, optimizer: SplatOptimizer, iteration: int,
                   generator: torch.Generator) -> dict:
        """:meth:`ADCStrategy.after_step` (densification until ``stop_iter``), then, after 0-based iteration
        ``prune_at - 1``, the one opacity prune of :func:`prune_below`.

        Returns the density-control statistics, with ``sugar_prune`` (splats removed) and ``n_splats`` (splats
        left) added at the prune's iteration.
        """
        stats = super().after_step(model, optimizer, iteration, generator)
        if iteration + 1 == self.prune_at:
            stats["sugar_prune"] = prune_below(model, optimizer, self.prune_opacity_hard)
            stats["n_splats"] = model.n_splats
            log.info("SuGaR prune after iteration %d: %d splats with opacity < %.3g removed, %d left",
                     self.prune_at, stats["sugar_prune"], self.prune_opacity_hard, model.n_splats)
        return stats
