"""Capacity per scene: choose the splat budget and field width from the scene, not from a table.

The search never looks at test views. It holds out some of the *training* views, trains short runs of
growing capacity on the rest, scores each on the held-out training views, and stops growing a
dimension when the held-out PSNR improves by less than ``min_gain_db``: "model no more than a scene
needs". The main run then trains on all training views with the chosen sizes, which are recorded in
``metrics.json`` (``capacity`` block, and ``keys.max_splats`` / ``keys.width``).
"""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from src.data.base import Scene
from src.eval.evaluator import Evaluator
from src.init.stage1 import ensure_first_stage
from src.trainer.fit import fit_scene
from src.utils.validate import ConfigValueError

log = logging.getLogger(__name__)



def has_field(cfg: DictConfig) -> bool:
    """Whether the configured model has neural fields (a backbone; field=none leaves an empty one)."""
    return OmegaConf.select(cfg, "model.network.backbone._target_") is not None


def has_triplane(cfg: DictConfig) -> bool:
    """Whether the backbone's tri-plane resolution follows ``field_budget.triplane_up_blocks``."""
    return (OmegaConf.select(cfg, "model.network.backbone.n_up_blocks") is not None
            and OmegaConf.select(cfg, "field_budget.triplane_up_blocks") is not None)


class FixedCapacity:
    """No search: the configured sizes are used as they are."""

    enabled = False


class CapacitySearch:
    """Greedy search over splat budgets, then head widths, then tri-plane resolution, on held-out
    training views. Each dimension grows (with the earlier ones fixed at their choice) until the gain
    falls below ``min_gain_db``; a dimension with a single candidate is taken without a trial.

    Args:
        budgets: candidate splat budgets (``schedule.max_splats`` and the initial point count), ascending.
        widths: candidate values of ``field_budget.head_width`` (the large heads' width; conf/model/
            splatfields.yaml gives the small heads half), ascending; ignored for models without fields.
        plane_blocks: candidate values of ``field_budget.triplane_up_blocks`` (tri-plane side
            20·2^k), ascending; ignored for backbones without tri-planes. Empty = keep the configured one.
        holdout_every: hold out every k-th training view (at least one) for validation.
        search_iterations: training iterations of each search run.
        min_gain_db: stop growing when the held-out PSNR improves by less than this.
    """

    enabled = True

    def __init__(self, budgets: list[int] = (2500, 5000, 10000, 20000), widths: list[int] = (32, 64, 128),
                 plane_blocks: list[int] = (), holdout_every: int = 4, search_iterations: int = 600,
                 min_gain_db: float = 0.1) -> None:
        self.budgets = sorted(budgets)
        self.widths = sorted(widths)
        self.plane_blocks = sorted(plane_blocks)
        self.holdout_every = holdout_every
        self.search_iterations = search_iterations
        self.min_gain_db = min_gain_db

    def split(self, scene: Scene) -> tuple[Scene, Scene]:
        """(training part, validation part) of the training views; the test views are never used."""
        val_idx = set(range(len(scene.train) - 1, -1, -self.holdout_every)) if len(scene.train) > 1 else set()
        if not val_idx:
            raise ConfigValueError("capacity=auto needs at least 2 training views to hold one out")
        train = [v for i, v in enumerate(scene.train) if i not in val_idx]
        val = [v for i, v in enumerate(scene.train) if i in val_idx]
        return replace(scene, train=train, test=val, val=[]), replace(scene, train=val, test=val, val=[])

    @staticmethod
    def apply(cfg: DictConfig, budget: int | None, width: int | None = None,
              plane_blocks: int | None = None) -> DictConfig:
        """A copy of ``cfg`` with the splat budget, ``field_budget.head_width`` and
        ``field_budget.triplane_up_blocks`` set (None = leave as configured).

        The heads and the backbone follow ``field_budget`` through the interpolations in
        conf/model/splatfields.yaml and conf/field/cnn_triplane.yaml, so ``cfg`` must not be resolved yet.
        """
        out = copy.deepcopy(cfg)
        with open_dict(out):
            if budget is not None:
                out.schedule.max_splats = int(budget)
                out.init.n_points = int(budget)
            if width is not None and has_field(out):
                if OmegaConf.select(out, "field_budget.head_width") is None:
                    raise ConfigValueError("capacity=auto: the config has no field_budget.head_width to search over "
                                     "(set by conf/scale/*.yaml)")
                out.field_budget.head_width = int(width)
            if plane_blocks is not None and has_triplane(out):
                out.field_budget.triplane_up_blocks = int(plane_blocks)
        return out

    @staticmethod
    def _own_first_stage(cfg: DictConfig, out_dir: Path) -> DictConfig:
        """For a two-stage config (``stage1.auto``), a copy whose first stage lives in ``out_dir/stage1``
        (trained on the search's training part only, so no held-out view leaks into the trials'
        initialisation) with its iterations pinned before the trials shorten the run; else ``cfg``."""
        if not (OmegaConf.select(cfg, "stage1.auto") and OmegaConf.select(cfg, "init.run_dir")):
            return cfg
        out = copy.deepcopy(cfg)
        with open_dict(out):
            out.stage1.iterations = int(cfg.stage1.iterations)
            out.init.run_dir = str(out_dir / "stage1")
        return out

    def _score(self, cfg: DictConfig, part: Scene, out_dir: Path, device, fit: Callable) -> dict:
        short = copy.deepcopy(cfg)
        with open_dict(short):
            short.trainer.iterations = self.search_iterations
            short.trainer.progress = False
            short.trainer.tensorboard = False
            short.trainer.ckpt_every = 0
            short.trainer.resume = False
        gen = torch.Generator().manual_seed(int(cfg.seed))
        model, rasterizer, stats = fit(short, part, out_dir, device, gen)
        scored = Evaluator(save_renders=False, train_views=False, moran=False, fps_repeats=0).score_views(
            model, rasterizer, part.test, part.background, None)
        return {"val_psnr": scored["psnr"], "n_splats": model.n_splats, "n_params": model.n_params(),
                "train_s": stats["train_s"]}

    def _grow(self, values, make_cfg, part, out_dir, device, fit, trace, label) -> object:
        best, best_psnr = values[0], -math.inf
        if len(values) == 1:
            return best
        for v in values:
            row = self._score(make_cfg(v), part, out_dir / f"{label}_{v}", device, fit)
            row[label] = v
            trace.append(row)
            log.info("capacity search: %s=%s -> held-out PSNR %.2f dB", label, v, row["val_psnr"])
            if row["val_psnr"] < best_psnr + self.min_gain_db:
                break
            best, best_psnr = v, row["val_psnr"]
        return best

    def choose(self, cfg: DictConfig, scene: Scene, out_dir: Path, device,
               fit: Callable | None = None) -> tuple[DictConfig, dict]:
        """Run the search; returns (cfg with the chosen sizes, the record's ``capacity`` block).

        ``fit`` trains one trial (default :func:`src.trainer.fit.fit_scene`, the way every run trains).
        """
        fit = fit or fit_scene
        part, val = self.split(scene)
        trace: list[dict] = []
        search_cfg = self._own_first_stage(cfg, out_dir)
        if search_cfg is not cfg:  # two-stage protocol: the trials start from a first stage of `part`
            ensure_first_stage(search_cfg, part, device, fit)
        budget = self._grow(self.budgets, lambda b: self.apply(search_cfg, b), part, out_dir, device, fit, trace,
                            "max_splats")
        chosen: dict = {"max_splats": int(budget)}
        if has_field(cfg):
            width = self._grow(self.widths, lambda w: self.apply(search_cfg, budget, w), part, out_dir, device, fit,
                               trace, "width")
            chosen["width"] = int(width)
            if self.plane_blocks and has_triplane(cfg):
                blocks = self._grow(self.plane_blocks, lambda p: self.apply(search_cfg, budget, width, p), part,
                                    out_dir, device, fit, trace, "triplane_up_blocks")
                chosen["triplane_up_blocks"] = int(blocks)
        new_cfg = self.apply(cfg, chosen["max_splats"], chosen.get("width"), chosen.get("triplane_up_blocks"))
        return new_cfg, {"chosen": chosen, "trace": trace, "holdout_views": [v.image_id for v in val.train],
                         "min_gain_db": self.min_gain_db}
