"""Densification strategies: when to add, split and remove splats.

Strategies only read screen-space gradients (``RenderOutput.means2d.grad``, pixels) and act through
the model's densification interface, so the same strategy drives free 3DGS splats and the
canonical query points of SplatFields. ``max_splats`` is a hard cap honoured by every strategy.
"""

from src.strategy.anchor import AnchorStrategy
from src.strategy.base import NoDensification, Strategy
from src.strategy.budget import BudgetStrategy
from src.strategy.default import ADCStrategy
from src.strategy.lightgaussian import LightGaussianStrategy
from src.strategy.sugar import SugarStrategy

__all__ = ["ADCStrategy", "AnchorStrategy", "BudgetStrategy", "LightGaussianStrategy", "NoDensification", "Strategy",
           "SugarStrategy"]
