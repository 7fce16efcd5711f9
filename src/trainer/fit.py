"""Train one configuration on a loaded scene: the components built from the config, then :class:`Trainer`."""

from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig

from src.sparse import optimizer_for
from src.trainer.identity import run_identity
from src.utils.instantiate import build, takes


def fit_scene(cfg: DictConfig, scene, run_dir: Path, device: torch.device, generator: torch.Generator):
    """Build the model, rasterizer, loss, strategy and optimiser from ``cfg`` and train on ``scene``.

    Returns (model, rasterizer, training statistics). The one way every run trains: the main run
    (``src.run``), a two-stage protocol's first stage (:mod:`src.init.stage1`) and each trial of a
    capacity search (:mod:`src.capacity`).
    """
    rasterizer = build(cfg.rasterizer)
    init_points = build(cfg.init)(scene, generator)

    def build_model():
        return build(cfg.model, init=init_points.to(device), n_frames=scene.n_frames).to(device)

    model = build_model()
    loss_fn = build(cfg.loss, **takes(cfg.loss, extent=scene.extent, generator=generator))  # those it takes
    strategy = build(cfg.strategy, extent=scene.extent)
    sparse = build(cfg.sparse) if cfg.get("sparse") else None  # training-free sparse-view ingredients (src/sparse)
    if sparse is not None and sparse.empty:
        sparse = None
    if sparse is not None:  # e.g. CoR-GS: a second model and strategy of the same configuration beside the first
        model, strategy = sparse.prepare(model, strategy, build_model,
                                         lambda: build(cfg.strategy, extent=scene.extent))
    optim_factory = build(cfg.optim)

    def make_optimizer(m):  # one optimiser per co-trained model (src.sparse.optimizer_for)
        return optimizer_for(m, lambda groups: optim_factory(groups=groups, extent=scene.extent))

    trainer = build(cfg.trainer)
    trainer.identity = run_identity(cfg, scene)  # checkpoints carry it; a resume of another run is refused
    scorer = build(cfg.eval).curve_scorer(scene, rasterizer) if cfg.eval.get("curve_every") else None
    stats = trainer.fit(model, scene, rasterizer, loss_fn, make_optimizer, strategy, run_dir, generator, seed=cfg.seed,
                        curve=scorer[1] if scorer else None, curve_every=int(cfg.eval.get("curve_every") or 0),
                        sparse=sparse)
    if scorer:
        stats["curve_split"] = scorer[0]
    if sparse is not None:  # CoR-GS: the first of the two co-trained models is the one evaluated
        model = sparse.final_model(model)
    return model, rasterizer, stats
