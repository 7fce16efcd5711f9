"""The first stage of the paper's two-stage Blender protocol, trained in-process when it is missing.

SplatFields3D on Blender scenes starts from the splat centres of a finished 3DGS run (reference
``run_blender.sh``: 3DGS, then SplatFields on its points). ``+experiment=splatfields3d_2stage`` reads
them from ``init.run_dir`` (``paths.stage1_dir``, one directory per scene / views / iterations / seed);
with ``stage1.auto=true`` a missing first stage is trained here, with exactly the configuration of
``+experiment=gs3d_stage1`` (``stage1.model/optim/strategy/init`` are the gs3d groups), so one command
runs both stages and a sweep needs no separate first pass.

Concurrency: jobs of one sweep that share a first stage (same scene, views, iterations, seed) take a
file lock; the first trains it in ``<dir>.partial/`` (checkpointed, so a killed job resumes it) and
renames it into place when done, the others wait and read it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from src.data.base import Scene
from src.io.ply import write_baked_ply
from src.trainer.fit import fit_scene
from src.utils.record import read_json, write_json
from src.utils.runlock import exclusive
from src.utils.seed import seed_everything
from src.utils.validate import ConfigValueError

log = logging.getLogger(__name__)

# What a first stage does not inherit from its second stage (the config's ``stage1.trainer`` /
# ``stage1.loss`` nodes are merged over these, and may change them): one view per step and the scene's own
# background (second-stage settings: a cached first stage stays the same whichever way they are set),
# L_norm and L_Moran off (as +experiment=gs3d).
FIRST_STAGE_OVERRIDES = {"trainer": {"views_per_step": 1, "random_background": False},
                         "loss": {"lambda_norm": 0.0, "lambda_moran": 0.0}}


def check_second_stage_init(cfg: DictConfig, init_choice: str | None) -> None:
    """Refuse, in one line, an initialiser chosen for the second stage of a two-stage run.

    A two-stage protocol's second stage always starts from its first stage's splats (``init=from_run``);
    ``init=sfm`` (or ``box``, ``hull``) on the command line means the first stage's start:
    ``init@stage1.init=sfm``. Without masks the first stage's hull already starts from the SfM points.
    """
    if cfg.get("stage1") is None or OmegaConf.select(cfg, "init._target_") == "src.init.FromRunInit":
        return
    name = init_choice or str(OmegaConf.select(cfg, "init._target_"))
    raise ConfigValueError(
        f"init={name}: experiment {cfg.get('experiment_name', 'default')!r} is two-stage, its second stage starts "
        f"from the first stage's splats (init=from_run); start the first stage from it with init@stage1.init={name}")


def first_stage_config(cfg: DictConfig) -> DictConfig:
    """``cfg`` with the model, optimiser, strategy, initialisation and losses of the first stage.

    Mirrors ``conf/experiment/gs3d.yaml`` (``stage1.method``: gs3d, or mip_splatting with
    ``protocol=two_stage_mip``): ``stage1.model`` / ``optim`` / ``strategy`` / ``init`` replace the run's;
    :data:`FIRST_STAGE_OVERRIDES`, then the (resolved) ``stage1.trainer`` and ``stage1.loss`` nodes
    (conf/protocol/two_stage.yaml), replace keys of the run's trainer and loss; ``stage1.iterations``;
    ``stage1.sparse`` (default ``none``) is its sparse-view ingredient, never the second stage's ``sparse``.
    """
    iterations = int(cfg.stage1.iterations)
    c = OmegaConf.create(OmegaConf.to_container(cfg, resolve=False))
    with open_dict(c):
        c.stage1.init.n_points = int(cfg.stage1.init.n_points)  # resolved before init is replaced below
        for group in ("model", "optim", "strategy", "init"):
            c[group] = c.stage1[group]
        for group in ("trainer", "loss"):  # resolved here: the stage1 node is gone below
            node = cfg.stage1.get(group)
            node = OmegaConf.to_container(node, resolve=True) if node is not None else {}
            c[group] = OmegaConf.merge(c[group], FIRST_STAGE_OVERRIDES[group], node)
        c.method = str(cfg.stage1.get("method", "gs3d"))
        c.trainer.iterations = iterations
        c.capacity = None
        c.sparse = c.stage1.get("sparse")  # the first stage's own ingredient (stage1.sparse), never the second stage's
        del c["stage1"]
    return c


def expected_keys(cfg: DictConfig, scene: Scene) -> dict:
    """What a usable first stage for ``cfg`` on ``scene`` must have been trained with.

    ``model`` is the first stage's model class (``stage1.model._target_``): a first stage of another
    model (e.g. ``model@stage1.model=mip_splatting``) in the same directory is refused, not re-used.
    ``image_size`` [W, H] of the first training view: renders of the same scene at another resolution
    share its name, and so its cache directory. ``settings``: :func:`settings_digest`.
    """
    return {"scene": scene.name, "n_views": len(scene.train), "seed": int(cfg.seed),
            "iterations": int(cfg.stage1.iterations), "n_points": int(cfg.stage1.init.n_points),
            "model": str(cfg.stage1.model.get("_target_")), "image_size": scene.image_size,
            "settings": settings_digest(cfg)}


def settings_digest(cfg: DictConfig) -> str:
    """A 12-digit digest of the first stage's optimiser and density control and of the ``stage1.trainer`` /
    ``stage1.loss`` nodes, resolved as the first stage sees them (its learning-rate horizon is its own
    iteration count, not the second stage's).

    A first stage trained with other settings (e.g. ``+stage1.trainer.random_background=true``) has another
    digest and is refused, not re-used; caches written without a digest are not checked.
    """
    c1 = first_stage_config(cfg)
    nodes = {"optim": c1.optim, "strategy": c1.strategy,
             **{g: cfg.stage1.get(g) for g in ("trainer", "loss")}}
    if has_ingredient(c1.get("sparse")):  # digests of first stages without one stay as they were
        nodes["sparse"] = c1.sparse
    nodes = {g: OmegaConf.to_container(n, resolve=True) if n is not None else None for g, n in nodes.items()}
    return hashlib.sha1(json.dumps(nodes, sort_keys=True, default=str).encode()).hexdigest()[:12]


def ingredient_slots(sparse: DictConfig | None) -> list[str]:
    """The ingredient slots a ``sparse`` node (conf/sparse/) sets (``none`` sets only its target: [])."""
    return [] if sparse is None else [str(k) for k, v in sparse.items() if k != "_target_" and v is not None]


def has_ingredient(sparse: DictConfig | None) -> bool:
    """Whether a ``sparse`` node sets any ingredient slot."""
    return bool(ingredient_slots(sparse))


def ingredient_tag(sparse: DictConfig | None) -> str:
    """``""``, or ``_`` and the set ingredient slots joined by ``+`` (``_dropout``): the suffix of a first
    stage's cache directory (``paths.stage1_dir``), so that first stages with and without an ingredient never
    share one."""
    slots = ingredient_slots(sparse)
    return "_" + "+".join(slots) if slots else ""


def check_first_stage(run_dir: Path, expected: dict) -> dict | None:
    """The first-stage record in ``run_dir``, or None if it has no ``splats.ply``.

    Raises ValueError naming the directory and the differing keys when it was trained for another setup.
    """
    if not (run_dir / "splats.ply").is_file():
        return None
    rec = read_json(run_dir / "metrics.json") or {}
    keys = rec.get("stage1_keys")
    if keys is None:  # written by `+experiment=gs3d_stage1` on the command line (its size: every run's record)
        keys = {**rec.get("keys", {}), "n_points": None, "image_size": rec.get("image_size")}
    diff = {k: (keys.get(k), v) for k, v in expected.items() if keys.get(k) is not None and keys.get(k) != v}
    if diff:
        raise ConfigValueError(f"{run_dir} holds a first stage trained with other settings "
                         f"({', '.join(f'{k}: {a} != {b}' for k, (a, b) in diff.items())}); "
                         "delete it or point paths.stage1_dir elsewhere")
    return rec


def ensure_first_stage(cfg: DictConfig, scene: Scene, device: torch.device,
                       fit: Callable | None = None) -> dict | None:
    """Make sure ``init.run_dir`` holds the first stage for this run; train it if missing.

    Args:
        cfg: the run's config; acts only when it has ``stage1.auto: true`` and ``init.run_dir``.
        scene: the loaded scene (the first stage trains on the same training views).
        fit: how to train it, ``(model, rasterizer, stats) = fit(cfg, scene, run_dir, device, generator)``;
            default :func:`src.trainer.fit.fit_scene`.

    Returns:
        ``{"dir", "train_s", "trained_now"}`` for the run record, or None when not applicable.
    """
    if not (cfg.get("stage1") and cfg.stage1.get("auto") and cfg.init.get("run_dir")):
        return None
    final = Path(str(cfg.init.run_dir))
    expected = expected_keys(cfg, scene)
    with exclusive(final.with_name(final.name + ".lock")):
        rec = check_first_stage(final, expected)
        trained_now = rec is None
        if trained_now:
            partial = final.with_name(final.name + ".partial")
            c1 = first_stage_config(cfg)
            method = str(c1.method)
            log.info("first stage missing: training %s for %d iterations in %s", method, expected["iterations"],
                     partial)
            model, _, stats = (fit or fit_scene)(c1, scene, partial, device, seed_everything(int(cfg.seed)))
            write_baked_ply(model, partial)
            rec = {"status": "ok", "method": method, "experiment": f"{method} first stage (in-process)",
                   "keys": {k: expected[k] for k in ("scene", "n_views", "seed", "iterations")},
                   "stage1_keys": expected, "metrics": {"train_s": stats["train_s"], "n_splats": model.n_splats}}
            write_json(partial / "metrics.json", rec)
            (partial / "checkpoint.pt").unlink(missing_ok=True)
            if final.exists():  # a half-written directory from an older layout: replace it
                shutil.rmtree(final)
            os.replace(partial, final)
    return {"dir": str(final), "train_s": (rec.get("metrics") or {}).get("train_s"), "trained_now": trained_now}
