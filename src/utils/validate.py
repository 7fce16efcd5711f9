"""Checks of a composed run config before anything is built: one line naming the key and what is expected.

Readers check their own files (poses, field of view, image sizes; see ``src/data``); this module
checks the numbers a user types on the command line: iteration counts, learning rates, splat
budgets, downscale factors.
"""

from __future__ import annotations

import math
from typing import Any

from omegaconf import DictConfig, OmegaConf

QUERY_SELECT = ("random", "opacity")  # init.select: how a two-stage run picks its query points (FromRunInit)


class ConfigValueError(ValueError):
    """A config value outside its valid range; the message names the key."""


def _number(value: Any) -> float | None:
    """``value`` as a float if it is a real number (not a bool), else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value)


def _require(cfg: DictConfig, key: str, integer: bool = False, allow_null: bool = True,
             minimum: float | None = None) -> None:
    """Check ``cfg.<key>`` (dotted) if present: a finite number > 0 (or >= ``minimum``), an integer if asked."""
    if OmegaConf.select(cfg, key, default="__absent__") == "__absent__":
        return
    value = OmegaConf.select(cfg, key)
    if value is None:
        if allow_null:
            return
        raise ConfigValueError(f"{key}=null: expected a number")
    x = _number(value)
    what = "a positive integer" if integer else "a positive number"
    if minimum is not None:
        what = f"{'an integer' if integer else 'a number'} >= {minimum:g}"
    if x is None or not math.isfinite(x) or (integer and x != int(x)):
        raise ConfigValueError(f"{key}={value!r}: expected {what}")
    if (minimum is not None and x < minimum) or (minimum is None and x <= 0):
        raise ConfigValueError(f"{key}={value!r}: expected {what}")


def compile_backend(value: bool | str | None) -> str | None:
    """The ``torch.compile`` backend named by ``trainer.compile``: None (false), "inductor" (true) or the name.

    Raises:
        ConfigValueError: naming ``trainer.compile`` and the backends torch knows, for an unknown name.
    """
    if value is None or value is False:
        return None
    if value is True:
        return "inductor"
    import torch

    known = torch.compiler.list_backends(exclude_tags=())
    if not isinstance(value, str) or value not in known:
        raise ConfigValueError(f"trainer.compile={value!r}: expected false, true or one of {known}")
    return value


def validate_run_config(cfg: DictConfig) -> None:
    """Raise :class:`ConfigValueError` for values no run can use (checked before the run starts).

    Iterations > 0; every learning rate (``optim.lr.<group>.init`` / ``final``) > 0; splat budgets
    (``init.n_points``, ``strategy.max_splats``, ``schedule.*``) > 0; ``dataset.n_views`` >= 1;
    ``dataset.downscale`` > 0; ``trainer.views_per_step`` >= 1; ``trainer.compile`` a known backend;
    ``init.select`` one of :data:`QUERY_SELECT`; ``trainer.random_background`` a boolean; ``seed`` an
    integer >= 0; ``threads`` null or a positive integer; the ``mesh`` node's own checks (it is built only
    after training, so it is built once here too: ``PoissonMesh`` holds nothing but its settings).
    """
    compile_backend(OmegaConf.select(cfg, "trainer.compile", default=None))
    select = OmegaConf.select(cfg, "init.select", default="random")
    if select not in QUERY_SELECT:
        raise ConfigValueError(f"init.select={select!r}: expected one of {', '.join(QUERY_SELECT)}")
    random_background = OmegaConf.select(cfg, "trainer.random_background", default=False)
    if not isinstance(random_background, bool):
        raise ConfigValueError(f"trainer.random_background={random_background!r}: expected true or false")
    _require(cfg, "trainer.iterations", integer=True, allow_null=False)
    _require(cfg, "trainer.views_per_step", integer=True)
    _require(cfg, "trainer.log_every", integer=True)
    for key in ("trainer.ckpt_every", "trainer.image_every"):
        _require(cfg, key, integer=True, minimum=0)
    lr = OmegaConf.select(cfg, "optim.lr")
    if isinstance(lr, DictConfig):
        for group in lr:
            node = lr[group]
            if isinstance(node, DictConfig):
                for part in ("init", "final"):
                    _require(cfg, f"optim.lr.{group}.{part}")
            else:
                _require(cfg, f"optim.lr.{group}")
    for key in ("schedule.init_points", "schedule.max_splats", "init.n_points", "strategy.max_splats"):
        _require(cfg, key, integer=True)
    _require(cfg, "dataset.n_views", integer=True)
    _require(cfg, "seed", integer=True, allow_null=False, minimum=0)
    _require(cfg, "threads", integer=True)  # null: torch's default; 0 or less has no meaning
    for key in ("dataset.downscale", "dataset.image_scale"):
        _require(cfg, key)
    if OmegaConf.select(cfg, "mesh._target_", default=None) is not None:
        from src.utils.instantiate import build  # imported here: the other checks need no hydra

        build(cfg.mesh)
