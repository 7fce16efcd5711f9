"""What a checkpoint belongs to, so that a resume never continues another run's training.

A checkpoint carries an *identity*: the experiment and method, the model class, the scene (its name
and a fingerprint of its training views: camera names, poses, intrinsics, image sizes, times) and
the resolved config sections that define the model and its data. Parameter shapes are read from the
state dicts themselves. :func:`mismatch` compares a stored identity with the current run's and says,
in one line, what differs.
"""

from __future__ import annotations

import hashlib
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

#: Config sections that define the model and its data (resolved, path-like keys left out).
IDENTITY_SECTIONS = ("model", "dataset", "init", "sparse")
#: Keys whose values are places on disk, not properties of the run (a moved dataset is the same data).
_PATH_SUFFIXES = ("root", "dir", "path", "_file")


def views_fingerprint(views: list) -> str:
    """A short hash of the training views: per view its camera name, time, image size, intrinsics and pose.

    ``views``: :class:`src.data.base.View` objects (OpenCV cameras, world-to-camera [4, 4]). Poses are
    rounded to 1e-5 so that the same files read on another host give the same fingerprint.
    """
    h = hashlib.sha256()
    for v in views:
        c = v.camera
        pose = [round(float(x), 5) for x in c.world_to_cam.detach().cpu().reshape(-1).tolist()]
        intr = [round(float(x), 3) for x in (c.fx, c.fy, c.cx, c.cy)]
        h.update(repr((c.name, round(float(c.time), 6), int(c.width), int(c.height), intr, pose)).encode())
    return h.hexdigest()[:16]


def _flatten(node: Any, prefix: str) -> dict[str, str]:
    """``{dotted.key: repr(value)}`` of a plain container, path-like keys left out."""
    if isinstance(node, dict):
        out: dict[str, str] = {}
        for k, v in node.items():
            if str(k).endswith(_PATH_SUFFIXES):
                continue
            out.update(_flatten(v, f"{prefix}.{k}"))
        return out
    return {prefix: repr(node)}


def config_identity(cfg: DictConfig) -> dict[str, str]:
    """The resolved values of :data:`IDENTITY_SECTIONS` as ``{dotted.key: repr(value)}``."""
    out: dict[str, str] = {}
    for section in IDENTITY_SECTIONS:
        node = OmegaConf.select(cfg, section, default=None)
        if node is None:
            continue
        plain = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node
        out.update(_flatten(plain, section))
    return out


def run_identity(cfg: DictConfig, scene) -> dict:
    """The identity of the run ``cfg`` trains on ``scene`` (stored in its checkpoints)."""
    return {
        "experiment": str(cfg.get("experiment_name", "default")), "method": str(cfg.get("method")),
        "model_class": str(OmegaConf.select(cfg, "model._target_", default="")),
        "scene": str(scene.name), "views": views_fingerprint(scene.train), "n_views": len(scene.train),
        "config": config_identity(cfg),
    }


def shape_mismatch(saved: dict[str, torch.Tensor], current: dict[str, torch.Tensor], saved_n: int,
                   current_n: int) -> str | None:
    """What differs between two state dicts' parameter names and shapes, or None.

    A per-splat tensor (first dimension = the splat count, ``saved_n`` in the checkpoint and
    ``current_n`` in the freshly built model) may differ in its sizes, not in its number of dimensions:
    densification changes the splat count and some methods the per-splat layout during training
    (LightGaussian distils its SH coefficients away); the network weights must match exactly. Entries
    only the checkpoint has are left to the model's ``load_state_dict``: some are created during
    training (LightGaussian's teacher buffers).
    """
    missing = sorted(set(current) - set(saved))
    if missing:
        return f"its parameters differ (missing {missing[:3]})"
    for k in current:
        a, b = tuple(saved[k].shape), tuple(current[k].shape)
        if a == b:
            continue
        per_splat = len(a) == len(b) and a[:1] == (saved_n,) and b[:1] == (current_n,)
        if not per_splat:
            return f"parameter {k} has shape {list(a)} there, {list(b)} here"
    return None


def mismatch(saved: dict | None, current: dict) -> str | None:
    """One phrase naming what differs between a checkpoint's identity ``saved`` and ``current``, or None."""
    if not isinstance(saved, dict):
        return "it carries no run identity (written by an older version of the project)"
    for key, what in (("experiment", "experiment"), ("method", "method"), ("model_class", "model class"),
                      ("scene", "scene"), ("n_views", "training view count"), ("views", "training views")):
        if saved.get(key) != current.get(key):
            return f"its {what} is {saved.get(key)!r}, this run's is {current.get(key)!r}"
    before, now = saved.get("config", {}), current.get("config", {})
    differ = [k for k in sorted(set(before) | set(now)) if before.get(k) != now.get(k)]
    if differ:
        k = differ[0]
        more = f" (and {len(differ) - 1} more)" if len(differ) > 1 else ""
        return f"{k} is {before.get(k, '<absent>')} there, {now.get(k, '<absent>')} here{more}"
    return None
