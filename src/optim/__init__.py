"""Optimisers and learning-rate schedules over named parameter groups.

Each model names its parameter groups (``means``, ``scales``, ``quats``, ``opacities``, ``sh0``,
``shN`` for 3DGS; ``network`` for SplatFields); the optimiser config gives each name a schedule.
"""

from src.optim.adam import LRSchedule, SplatOptimizer, replace_param_rows

__all__ = ["LRSchedule", "SplatOptimizer", "replace_param_rows"]
