"""The one place where Hydra configs become objects.

Every component (dataset, model, rasterizer, loss, ...) is built here so that a future change in
Hydra's instantiate rules (e.g. the 1.4 ``_target_`` allow-list) is a one-line edit.
"""

from __future__ import annotations

from typing import Any

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

TARGET_PREFIXES = ("src.", "torch.", "functools.")


def build(cfg: DictConfig | dict, **kwargs: Any) -> Any:
    """Instantiate ``cfg`` (a node with ``_target_``), passing runtime-only objects as ``kwargs``.

    Raises:
        ValueError: if the node has no ``_target_`` or it points outside the allowed packages.
    """
    target = cfg.get("_target_") if isinstance(cfg, dict | DictConfig) else None
    if target is None:
        keys = list(cfg.keys()) if isinstance(cfg, dict | DictConfig) else type(cfg).__name__
        raise ValueError(f"cannot build a component from a config without _target_ (keys: {keys})")
    if not str(target).startswith(TARGET_PREFIXES):
        raise ValueError(f"_target_ {target!r} is outside the allowed packages {TARGET_PREFIXES}")
    if isinstance(cfg, dict):
        cfg = OmegaConf.create(cfg)
    return instantiate(cfg, _convert_="all", **kwargs)
