"""The training loop: view sampling, loss, backward, densification, guards, checkpoints, logging.

Conventions: iterations count from 0; a checkpoint saved after iteration i resumes at i + 1.
Times are wall-clock seconds (``time.perf_counter``); images [H, W, C] in [0, 1].
"""

from src.trainer.guard import DivergenceError, DivergenceGuard
from src.trainer.trainer import Trainer

__all__ = ["DivergenceError", "DivergenceGuard", "Trainer"]
