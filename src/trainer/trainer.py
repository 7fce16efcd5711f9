"""The optimisation loop shared by every method."""

from __future__ import annotations

import logging
import math
import random
import time
from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from tqdm import tqdm

from src.data.base import Scene, View
from src.models.base import SplatModel
from src.optim.adam import SplatOptimizer
from src.rasterizer.base import Rasterizer
from src.sparse.base import SparseIngredient
from src.strategy.base import Strategy
from src.trainer.guard import DivergenceError, DivergenceGuard
from src.trainer.identity import mismatch, shape_mismatch
from src.utils.interrupt import RunInterrupted, set_deferred, stop_requested
from src.utils.record import atomic_write_bytes
from src.utils.validate import compile_backend

if TYPE_CHECKING:
    from torch.utils.tensorboard import SummaryWriter

log = logging.getLogger(__name__)


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be resumed from; the message names the file and the way out."""


CHECKPOINT_KEYS = ("iteration", "model", "optimizer", "strategy", "py_rng", "torch_rng", "np_rng", "generator",
                   "extra")


def numpy_rng_state() -> dict:
    """numpy's global (legacy) RNG state as plain types and a tensor, loadable with ``weights_only=True``."""
    name, keys, pos, has_gauss, cached = np.random.get_state()  # noqa: NPY002 - libraries use the global RNG
    return {"name": str(name), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)), "pos": int(pos),
            "has_gauss": int(has_gauss), "cached_gaussian": float(cached)}


def set_numpy_rng_state(state: dict) -> None:
    """Restore what :func:`numpy_rng_state` stored."""
    keys = state["keys"].numpy().astype(np.uint32)
    np.random.set_state((state["name"], keys, state["pos"], state["has_gauss"],  # noqa: NPY002
                         state["cached_gaussian"]))


def _mse_psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    mse = float(((a.detach() - b) ** 2).mean())
    return math.inf if mse == 0 else -10 * math.log10(mse)


@dataclass
class _Fit:
    """One call of :meth:`Trainer.fit`: what it trains with, and what it carries from step to step (and
    across a resume: the timing sums, the curve, the training time so far)."""

    model: SplatModel
    scene: Scene
    rasterizer: Rasterizer
    loss_fn: Callable
    optimizer: SplatOptimizer
    strategy: Strategy
    sparse: SparseIngredient | None
    guard: DivergenceGuard
    rng: random.Random  # view sampling
    generator: torch.Generator  # every other draw of the run
    ckpt_path: Path
    writer: SummaryWriter | None = None  # None without ``tensorboard``
    start: int = 0  # the first iteration of this call (a resumed checkpoint's iteration + 1)
    prev_train_s: float = 0.0  # training seconds before this call (those of a resumed run)
    t_start: float = 0.0  # perf_counter() at this call's start, moved on by the time spent scoring the curve
    timing: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))  # seconds per part
    n_timed: int = 0  # steps summed in ``timing``
    points: list[dict] = field(default_factory=list)  # the curve: [{iteration, wall_s, psnr}]
    psnr: float = math.nan  # the last step's training PSNR

    def train_s(self) -> float:
        """Training seconds so far (a resumed run's included, curve scoring excluded)."""
        return self.prev_train_s + time.perf_counter() - self.t_start

    def extra(self) -> dict:
        """What a resume needs besides the model, optimiser, strategy and RNG states (a checkpoint's ``extra``)."""
        return {"train_s": self.train_s(), "guard_running_psnr": self.guard.running_psnr, "curve": self.points,
                "timing": dict(self.timing), "n_timed": self.n_timed}


class Trainer:
    """Trains a :class:`SplatModel` on a :class:`Scene`.

    Args:
        iterations: optimisation steps.
        views_per_step: training views rendered per step; for dynamic scenes they share one time
            (the paper's 4D protocol renders 5 views of one frame and averages their losses).
        log_every: TensorBoard / progress-bar update interval.
        image_every: TensorBoard image interval (0 = never).
        ckpt_every: checkpoint interval (0 = only at the end). Checkpoints are written atomically.
        resume: resume from ``<run>/checkpoint.pt`` if it exists; false = start fresh, keeping an existing
            checkpoint aside as ``checkpoint.pt.<timestamp>.old``.
        progress: show a tqdm progress bar.
        tensorboard: write TensorBoard scalars and images under ``<run>/tb``.
        guard: divergence-guard settings (see :class:`DivergenceGuard`).
        compile: ``torch.compile`` the forward of the model's networks (:meth:`SplatModel.networks`) before
            training: false (eager), true (the inductor backend) or a backend name (e.g. ``"eager"``,
            ``"aot_eager"``). State dicts are unchanged, so checkpoints load either way.
        random_background: train every step on a uniformly random background colour (the training
            images re-composited with their masks, the renders on the same colour), as the 3DGS code's
            ``--random_background``; evaluation keeps the scene's background. Needs masked views.
    """

    def __init__(self, iterations: int = 30_000, views_per_step: int = 1, log_every: int = 50,
                 image_every: int = 0, ckpt_every: int = 0, resume: bool = True, progress: bool = True,
                 tensorboard: bool = True, guard: dict | None = None, compile: bool | str = False,
                 random_background: bool = False) -> None:
        self.iterations = iterations
        self.views_per_step = views_per_step
        self.log_every = log_every
        self.image_every = image_every
        self.ckpt_every = ckpt_every
        self.resume = resume
        self.progress = progress
        self.tensorboard = tensorboard
        self.guard_cfg = dict(guard or {})
        self.compile = compile_backend(compile)
        self.random_background = bool(random_background)
        self.identity: dict | None = None  # the run's identity, stored in and checked against checkpoints

    # -- torch.compile -----------------------------------------------------------------------
    def compile_networks(self, model: SplatModel) -> list[str]:
        """Compile the forward of every network of ``model`` in place (``trainer.compile``); their class names."""
        if self.compile is None:
            return []
        names = []
        for net in model.networks():
            net.compile(backend=self.compile, dynamic=True)  # nn.Module.compile: the state dict keeps its keys
            names.append(type(net).__name__)
        what = ", ".join(names) or f"nothing ({type(model).__name__} has no network)"
        log.info("trainer.compile=%s: compiled %s", self.compile, what)
        return names

    # -- view sampling -----------------------------------------------------------------------
    @staticmethod
    def views_by_frame(scene: Scene) -> list[list[View]]:
        """Training views grouped by frame id, in frame order (one group for static scenes)."""
        by_frame: dict[int, list[View]] = defaultdict(list)
        for v in scene.train:
            by_frame[v.camera.frame_id].append(v)
        return [by_frame[f] for f in sorted(by_frame)]

    def sample_views(self, groups: list[list[View]], rng: random.Random) -> list[View]:
        """Random training views for one step: one random frame, then up to ``views_per_step`` of its views."""
        views = groups[rng.randrange(len(groups))]
        k = min(self.views_per_step, len(views))
        return rng.sample(views, k)

    # -- checkpoints -------------------------------------------------------------------------
    @staticmethod
    def save_checkpoint(path: Path, model: SplatModel, optimizer: SplatOptimizer, strategy: Strategy,
                        iteration: int, rng: random.Random, generator: torch.Generator, extra: dict,
                        identity: dict | None = None) -> None:
        """Write ``path`` atomically, holding only what ``torch.load(weights_only=True)`` reads back.

        Tensors, numbers, strings, None and dicts / lists / tuples of them: the RNG states are stored
        as such (numpy's legacy state as a dict with a tensor of keys), so loading runs no code.
        ``identity`` (:func:`src.trainer.identity.run_identity`) says which run the checkpoint belongs to.
        """
        import io

        buf = io.BytesIO()
        torch.save({
            "iteration": iteration, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "strategy": strategy.state_dict(), "py_rng": rng.getstate(), "torch_rng": torch.get_rng_state(),
            "np_rng": numpy_rng_state(), "generator": generator.get_state(), "extra": extra,
            "identity": identity, "n_splats": model.n_splats,
        }, buf)
        atomic_write_bytes(path, buf.getvalue())

    @staticmethod
    def load_checkpoint(path: Path) -> dict:
        """Read a checkpoint with ``weights_only=True`` (no code runs); CheckpointError names the file."""
        try:
            ck = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # truncated, corrupt, or holding types the safe loader refuses
            raise CheckpointError(
                f"{path}: cannot read this checkpoint ({type(e).__name__}: {str(e).splitlines()[0][:200]}); "
                "to start fresh and keep it aside, re-run with trainer.resume=false") from None
        missing = [k for k in CHECKPOINT_KEYS if not isinstance(ck, dict) or k not in ck]
        if missing:
            raise CheckpointError(f"{path}: not a checkpoint of this project (missing {missing}); to start fresh "
                                  "and keep it aside, re-run with trainer.resume=false")
        return ck

    def check_identity(self, path: Path, ck: dict, model: SplatModel) -> None:
        """Refuse, in one line, a checkpoint of another run (experiment, model, scene, config or shapes).

        Checked only when the trainer knows its run (``self.identity``, set by ``src.trainer.fit.fit_scene``).
        """
        if self.identity is None:
            return
        why = mismatch(ck.get("identity"), self.identity) or shape_mismatch(
            ck["model"], model.state_dict(), int(ck.get("n_splats", -1)), model.n_splats)
        if why:
            raise CheckpointError(f"{path} belongs to another run: {why}; to train this run from scratch "
                                  "(keeping that checkpoint aside), re-run with trainer.resume=false")

    @staticmethod
    def set_aside(path: Path) -> Path | None:
        """Rename an existing checkpoint to ``<name>.<timestamp>.old`` (never deleted); returns the new path."""
        if not path.is_file():
            return None
        stamp = time.strftime("%Y%m%d-%H%M%S")
        target = path.with_name(f"{path.name}.{stamp}.old")
        k = 1
        while target.exists():
            target, k = path.with_name(f"{path.name}.{stamp}-{k}.old"), k + 1
        path.rename(target)
        log.info("trainer.resume=false: kept the previous checkpoint aside as %s", target)
        return target

    # -- one optimisation step ------------------------------------------------------------------
    @staticmethod
    def train_step(model: SplatModel, views: list[View], rasterizer: Rasterizer, loss_fn: Callable,
                   optimizer: SplatOptimizer, strategy: Strategy, guard: DivergenceGuard, it: int,
                   generator: torch.Generator, background: torch.Tensor, *,
                   sparse: SparseIngredient | None = None) -> dict:
        """Render ``views``, back-propagate the loss, step the optimiser and the strategy.

        The loss is the objective's ``total`` plus the model's :meth:`SplatModel.regularisers`.
        ``sparse`` (the ``sparse`` config group's ingredients) may change the splats rendered, add loss
        terms (counted in the rasterizer's time) and change the model after the strategy.
        Returns dict(terms, renders, dens (strategy stats), psnr (mean over views), lrs, timing) where
        timing holds seconds spent in field (splat prediction), rasterizer (forward), backward and
        optimizer (optimiser + strategy).
        """
        t0 = time.perf_counter()
        model.on_step(it)
        lrs = optimizer.set_step(it)
        cams = [v.camera for v in views]
        splats = model.splats_for(cams)
        if sparse is not None:
            splats = sparse.train_splats(model, splats, it, generator)
        t1 = time.perf_counter()
        renders = [rasterizer.render(s, c, background) for s, c in zip(splats, cams, strict=True)]
        for r in renders:
            if r.means2d.requires_grad:
                r.means2d.retain_grad()
        extra = {} if sparse is None else sparse.loss_terms(model, views, renders, rasterizer, background, it,
                                                            generator)
        t2 = time.perf_counter()
        terms = loss_fn(renders, views, splats, iteration=it)
        guard.check_loss(terms["total"], it)
        if not terms["total"].requires_grad:  # nothing of the model reached any rendered pixel
            raise DivergenceError(f"collapse: no splat is visible in the training view(s) "
                                  f"{[c.name for c in cams]} at iteration {it} (the loss has no gradient)")
        if extra:
            terms = {**terms, **extra, "total": terms["total"] + sum(extra.values())}
            guard.check_loss(terms["total"], it)
        reg = model.regularisers(it)  # e.g. 4DGaussians' plane TV: terms of the model's parameters, not of renders
        if reg:
            terms = {**terms, **reg, "total": terms["total"] + sum(reg.values())}
            guard.check_loss(terms["total"], it)
        terms["total"].backward()
        t3 = time.perf_counter()
        guard.check_gradients(model.parameters(), it)
        strategy.after_backward(model, renders, it)
        optimizer.step()
        optimizer.zero_grad()
        dens = strategy.after_step(model, optimizer, it, generator)
        if sparse is not None:
            dens = {**dens, **sparse.after_step(model, optimizer, it, generator)}
        guard.check_splats(model.n_splats, it)
        t4 = time.perf_counter()
        psnr = sum(_mse_psnr(r.color, v.image) for r, v in zip(renders, views, strict=True)) / len(views)
        guard.check_psnr(psnr, it)
        timing = {"field": t1 - t0, "rasterizer": t2 - t1, "backward": t3 - t2, "optimizer": t4 - t3}
        return {"terms": terms, "renders": renders, "dens": dens, "psnr": psnr, "lrs": lrs, "timing": timing}

    # -- main loop ---------------------------------------------------------------------------
    def fit(self, model: SplatModel, scene: Scene, rasterizer: Rasterizer, loss_fn: Callable,
            make_optimizer: Callable[[SplatModel], SplatOptimizer], strategy: Strategy, run_dir: Path,
            generator: torch.Generator, seed: int = 0, curve: Callable[[SplatModel], float] | None = None,
            curve_every: int = 0, sparse: SparseIngredient | None = None) -> dict:
        """Optimise ``model``; returns training statistics (train_s, iter_ms, timing split, ...).

        With ``curve`` and ``curve_every`` > 0, ``curve(model)`` (a held-out PSNR) is recorded every
        ``curve_every`` iterations and after the last one, as ``curve``: [{iteration, wall_s, psnr}],
        ``wall_s`` being the training time so far (the scoring itself is not counted).
        ``sparse``: the training-free sparse-view ingredients applied in every step (:mod:`src.sparse`),
        bound to the model, scene and rasterizer before a checkpoint is resumed; they keep no state of
        their own (their randomness is ``generator``'s, which the checkpoint holds).
        """
        run_dir = Path(run_dir)
        ckpt_path = run_dir / "checkpoint.pt"
        rng = random.Random(seed)
        if self.random_background and any(v.mask is None for v in scene.train):
            raise ValueError(f"trainer.random_background=true needs masked training views; "
                             f"those of {scene.name} have none")
        guard = DivergenceGuard(**self.guard_cfg)
        fit = _Fit(model=model, scene=scene, rasterizer=rasterizer, loss_fn=loss_fn, optimizer=make_optimizer(model),
                   strategy=strategy, sparse=sparse, guard=guard, rng=rng, generator=generator, ckpt_path=ckpt_path)
        self._bind(fit)
        if not self.resume:
            self.set_aside(ckpt_path)
        elif ckpt_path.is_file():
            self._resume_from(fit, make_optimizer)
        if self.tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            # purge_step: TensorBoard drops the killed run's events from `start` on (no doubled curves).
            fit.writer = SummaryWriter(str(run_dir / "tb"), purge_step=fit.start or None)
        fit.t_start = time.perf_counter()
        bar = tqdm(range(fit.start, self.iterations), disable=not self.progress, dynamic_ncols=True,
                   desc=f"train {getattr(model, 'method', '')}", initial=fit.start, total=self.iterations)
        groups = self.views_by_frame(scene)
        deferred_before = set_deferred(True)  # a signal now stops the loop between steps (src/utils/interrupt.py)
        for it in bar:
            views, step = self._step(fit, groups, it)
            self._log_step(fit, bar, it, views, step)
            if curve is not None and curve_every > 0 and ((it + 1) % curve_every == 0 or it == self.iterations - 1):
                self._record_curve(fit, curve, it)
            self._checkpoint_step(fit, bar, it)
        set_deferred(deferred_before)
        bar.close()
        return self._finish(fit)

    def _bind(self, fit: _Fit) -> None:
        """Bind the model, its networks' compilation, the strategy and the sparse ingredients to the scene."""
        fit.model.bind(fit.scene)
        self.compile_networks(fit.model)
        fit.strategy.bind(fit.scene, fit.rasterizer)
        if fit.sparse is not None:
            fit.sparse.bind(fit.model, fit.scene, fit.rasterizer, self.iterations)

    def _resume_from(self, fit: _Fit, make_optimizer: Callable[[SplatModel], SplatOptimizer]) -> None:
        """Restore ``fit`` from its checkpoint: model, a new optimiser with its state, strategy, RNGs, counters."""
        path = fit.ckpt_path
        ck = self.load_checkpoint(path)
        self.check_identity(path, ck, fit.model)
        try:
            fit.model.load_state_dict(ck["model"])
        except (RuntimeError, KeyError) as e:  # a layout the identity did not tell apart
            raise CheckpointError(f"{path}: its model state does not fit this model "
                                  f"({str(e).splitlines()[0][:200]}); to start fresh and keep it aside, "
                                  "re-run with trainer.resume=false") from None
        fit.optimizer = make_optimizer(fit.model)
        try:
            fit.optimizer.load_state_dict(ck["optimizer"])
        except ValueError as e:  # another parameter list (e.g. saved by a version with another network layout)
            raise CheckpointError(f"{path}: its optimiser state does not match this model's parameters ({e}); "
                                  "to start fresh and keep it aside, re-run with trainer.resume=false") from None
        fit.strategy.load_state_dict(ck["strategy"])
        fit.rng.setstate(ck["py_rng"])
        torch.set_rng_state(ck["torch_rng"])
        set_numpy_rng_state(ck["np_rng"])
        fit.generator.set_state(ck["generator"])
        fit.start = ck["iteration"] + 1
        extra = ck["extra"]
        fit.prev_train_s = extra.get("train_s", 0.0)
        # Resume = the uninterrupted run: the guard's running PSNR decides when a run fails, and the
        # timing sums make iter_ms cover the whole run (and defined if only evaluation was left).
        fit.guard.running_psnr = extra.get("guard_running_psnr")
        fit.timing = defaultdict(float, extra.get("timing", {}))
        fit.n_timed = extra.get("n_timed", 0)
        fit.points = list(extra.get("curve", []))
        log.info("resumed from %s at iteration %d", path, fit.start)

    def _step(self, fit: _Fit, groups: list[list[View]], it: int) -> tuple[list[View], dict]:
        """One optimisation step at iteration ``it``: its views (on a random background if asked) and
        :meth:`train_step`'s result; its time joins the timing sums (not the first step's)."""
        views = fit.strategy.step_views(fit.model, self.sample_views(groups, fit.rng), it, fit.generator)
        background = fit.scene.background
        if self.random_background:
            background = torch.rand(3, generator=fit.generator).to(fit.scene.background)
            views = [v.on_background(background, fit.scene.background) for v in views]
        step = self.train_step(fit.model, views, fit.rasterizer, fit.loss_fn, fit.optimizer, fit.strategy, fit.guard,
                               it, fit.generator, background, **({} if fit.sparse is None else {"sparse": fit.sparse}))
        fit.psnr = step["psnr"]
        if it > fit.start:  # the first iteration includes one-off costs (JIT build, caches)
            for k, v in step["timing"].items():
                fit.timing[k] += v
            fit.n_timed += 1
        return views, step

    def _log_step(self, fit: _Fit, bar: tqdm, it: int, views: list[View], step: dict) -> None:
        """Progress bar, log line and TensorBoard scalars every ``log_every`` steps; images every ``image_every``."""
        writer, model = fit.writer, fit.model
        if it % self.log_every == 0 or it == self.iterations - 1:
            loss = float(step["terms"]["total"].detach())
            bar.set_postfix(loss=f"{loss:.4f}", psnr=f"{fit.psnr:.2f}", n=model.n_splats)
            if not self.progress:
                log.info("iter %d/%d loss %.4f psnr %.2f splats %d", it, self.iterations, loss, fit.psnr,
                         model.n_splats)
            if writer is not None:
                for k, v in step["terms"].items():
                    writer.add_scalar(f"loss/{k}", float(v.detach()), it)
                writer.add_scalar("train/psnr", fit.psnr, it)
                writer.add_scalar("train/n_splats", model.n_splats, it)
                for k, v in step["lrs"].items():
                    writer.add_scalar(f"lr/{k}", v, it)
                for k, v in step["dens"].items():
                    writer.add_scalar(f"densify/{k}", v, it)
        if writer is not None and self.image_every and it % self.image_every == 0:
            writer.add_image("train/render", step["renders"][0].color.detach().clamp(0, 1), it, dataformats="HWC")
            writer.add_image("train/gt", views[0].image, it, dataformats="HWC")

    @staticmethod
    def _record_curve(fit: _Fit, curve: Callable[[SplatModel], float], it: int) -> None:
        """Score the model with ``curve`` after iteration ``it``; the scoring time is not training time."""
        t_curve = time.perf_counter()
        value = curve(fit.model)
        fit.points.append({"iteration": it + 1, "wall_s": fit.prev_train_s + t_curve - fit.t_start, "psnr": value})
        if fit.writer is not None:
            fit.writer.add_scalar("heldout/psnr", value, it)
        fit.t_start += time.perf_counter() - t_curve

    def _save(self, fit: _Fit, iteration: int, extra: dict) -> None:
        """Write the checkpoint of ``fit`` after ``iteration`` with ``extra`` (:meth:`_Fit.extra`)."""
        self.save_checkpoint(fit.ckpt_path, fit.model, fit.optimizer, fit.strategy, iteration, fit.rng, fit.generator,
                             extra, self.identity)

    def _checkpoint_step(self, fit: _Fit, bar: tqdm, it: int) -> None:
        """The periodic checkpoint (``ckpt_every``); on SIGINT / SIGTERM a checkpoint and RunInterrupted."""
        if self.ckpt_every and (it + 1) % self.ckpt_every == 0 and it + 1 < self.iterations:
            self._save(fit, it, fit.extra())
        if stop_requested() is not None:  # SIGINT / SIGTERM: stop after a whole step, resumable from here
            bar.close()
            self._save(fit, it, fit.extra())
            raise RunInterrupted(stop_requested(), it + 1)

    def _finish(self, fit: _Fit) -> dict:
        """The last checkpoint (if this call trained) and the statistics :meth:`fit` returns."""
        train_s = fit.train_s()
        if self.iterations > fit.start:
            self._save(fit, self.iterations - 1, {**fit.extra(), "train_s": train_s})
        if fit.writer is not None:
            fit.writer.close()
        n = max(fit.n_timed, 1)
        split = {f"{k}_ms": 1000 * v / n for k, v in fit.timing.items()}
        iter_ms = sum(split.values()) if fit.n_timed else math.nan
        return {"train_s": train_s, "iter_ms": iter_ms, "timing": split, "final_train_psnr": fit.psnr,
                "resumed_from": fit.start, "curve": fit.points}
