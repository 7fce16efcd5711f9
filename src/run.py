"""Entry point: ``python -m src.run [+experiment=NAME] [group=option ...] [key=value ...] [+ci=smoke]``.

Builds every component from its config group through :func:`src.utils.instantiate.build`, trains,
evaluates and writes the run record ``metrics.json`` (atomically, also when the run fails).
"""

from __future__ import annotations

import logging
import time
import traceback
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from src.init.stage1 import ensure_first_stage
from src.io.ply import write_baked_ply
from src.trainer.guard import DivergenceError
from src.utils.instantiate import build
from src.utils.memory import peak_memory_mb
from src.utils.record import env_info, read_json, write_json
from src.utils.seed import seed_everything

log = logging.getLogger("src.run")
REPO_ROOT = Path(__file__).resolve().parents[1]
if not OmegaConf.has_resolver("repo"):
    OmegaConf.register_new_resolver("repo", lambda: str(REPO_ROOT))
if not OmegaConf.has_resolver("basename"):
    OmegaConf.register_new_resolver("basename", lambda p: Path(str(p)).name)
if not OmegaConf.has_resolver("half"):  # narrow heads are half the width of the wide ones (B.2: 64 vs 128)
    OmegaConf.register_new_resolver("half", lambda w: max(8, int(w) // 2))


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda if available else cpu; otherwise the named device."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def hydra_context() -> dict:
    """Group choices, overrides and output dir of the current Hydra job (empty outside Hydra)."""
    try:
        hc = HydraConfig.get()
    except ValueError:
        return {"choices": {}, "overrides": [], "output_dir": None}
    choices = {k: v for k, v in OmegaConf.to_container(hc.runtime.choices).items()
               if not k.startswith("hydra/") and v is not None}
    return {"choices": choices, "overrides": list(hc.overrides.task), "output_dir": hc.runtime.output_dir}


def run(cfg: DictConfig, run_dir: Path | None = None) -> dict:
    """Train and evaluate one configuration; returns the run record (also written to metrics.json)."""
    ctx = hydra_context()
    run_dir = Path(run_dir or ctx["output_dir"] or cfg.paths.output_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    metrics_path = run_dir / "metrics.json"
    previous = read_json(metrics_path)
    # Resume safety (sweeps/README.md, "Resume"): a re-used run dir must hold the SAME job. A sweep
    # re-run with changed parameters renumbers its jobs, and skipping an "ok" record or resuming a
    # checkpoint of another configuration would silently attribute results to the wrong config.
    if previous and ctx["output_dir"] is not None and previous.get("overrides") is not None:
        before, now = _identity_overrides(previous["overrides"]), _identity_overrides(ctx["overrides"])
        if before != now:
            raise RuntimeError(
                f"{run_dir} holds another run (overrides {before}); this job has {now}. Re-use a run/sweep "
                "dir only with the same command; to extend a sweep use a new hydra.sweep.dir and pass both "
                "directories to src.tables.")
    if cfg.get("skip_if_done", True) and previous and previous.get("status") == "ok":
        log.info("%s already says status ok: skipping (set skip_if_done=false to re-run)", metrics_path)
        return previous
    # A run killed (SIGKILL) inside an atomic write leaves its temporary file (.NAME.XXXX.tmp, see
    # src/utils/record.py); the run dir belongs to this job alone, so drop such leftovers.
    for stale in run_dir.glob(".*.tmp"):
        stale.unlink(missing_ok=True)
    device = resolve_device(cfg.device)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    record: dict = {
        "status": "running", "error": None, "reason": None,
        "experiment": cfg.get("experiment_name", "default"), "method": cfg.method,
        "choices": ctx["choices"], "overrides": ctx["overrides"],
        # scene: the root's folder name until the reader names it, so unfinished runs sit in their row
        "keys": {"scene": Path(str(cfg.dataset.root)).name or None, "n_views": cfg.dataset.get("n_views"),
                 "seed": cfg.seed, "iterations": cfg.trainer.iterations,
                 # resolved: sweeps copy swept values into the keys, e.g. ${schedule.max_splats}
                 **OmegaConf.to_container(cfg.get("extra_keys", {}), resolve=True)},
        "metrics": {}, "views": [], "report": OmegaConf.to_container(cfg.report) if cfg.get("report") else None,
        "env": env_info(device), "run_dir": str(run_dir),
    }
    # Written now with status "running" (never "ok" before the end): a killed run leaves this record,
    # so tables list it as not finished and a re-run can check it is the same job (above).
    write_json(metrics_path, record)
    t0 = time.perf_counter()
    try:
        generator = seed_everything(cfg.seed)
        dataset = build(cfg.dataset)
        scene = dataset.load().to(device)
        record["keys"]["scene"] = scene.name
        record["views"] = scene.view_ids
        stage1 = ensure_first_stage(cfg, scene, device, fit_scene)  # two-stage protocol, stage1.auto
        if stage1 is not None:
            record["stage1"] = stage1
            generator = seed_everything(cfg.seed)  # the same stream whether stage 1 was trained or read
        capacity = build(cfg.capacity) if cfg.get("capacity") else None
        if capacity is not None and capacity.enabled:
            t_search = time.perf_counter()
            cfg, record["capacity"] = capacity.choose(cfg, scene, run_dir / "capacity", device, fit_scene)
            record["capacity"]["search_s"] = time.perf_counter() - t_search
            record["keys"].update(record["capacity"]["chosen"])
        model, rasterizer, train_stats = fit_scene(cfg, scene, run_dir, device, generator)
        evaluator = build(cfg.eval)
        ev = evaluator.evaluate(model, rasterizer, scene, run_dir)
        if cfg.trainer.get("tensorboard", False):
            evaluator.log_images(run_dir, model, rasterizer, scene, step=int(cfg.trainer.iterations))
        per_view = ev.pop("per_view_test")
        per_frame = ev.pop("per_frame", None)
        unavailable = ev.pop("unavailable_metrics", None)
        record["metrics"] = {
            "psnr": ev.pop("psnr"), "ssim": ev.pop("ssim"), "n_splats": model.n_splats,
            "n_params": model.n_params(), "train_s": train_stats["train_s"], "iter_ms": train_stats["iter_ms"],
            "peak_mem_mb": peak_memory_mb(device), **ev,
            **{f"iter_{k}": v for k, v in train_stats["timing"].items()},
        }
        if stage1 is not None:  # the 3DGS first stage is part of this method's training cost
            record["metrics"]["stage1_train_s"] = stage1["train_s"]
        if "capacity" in record:  # so is the capacity search
            record["metrics"]["capacity_search_s"] = record["capacity"]["search_s"]
        record["per_view"] = per_view
        if per_frame is not None:
            record["per_frame"] = per_frame
        if unavailable:
            record["unavailable_metrics"] = unavailable  # e.g. LPIPS without user-supplied backbone weights
        record["rasterizer"] = getattr(rasterizer, "name", type(rasterizer).__name__)
        write_baked_ply(model, run_dir)
        record["status"] = "ok"
        log.info("test PSNR %.2f dB, SSIM %.4f, %d splats, %.1f s", record["metrics"]["psnr"],
                 record["metrics"]["ssim"], model.n_splats, record["metrics"]["train_s"])
    except DivergenceError as e:
        record.update(status="failed", reason=f"divergence: {e}", error=str(e))
        log.error("run diverged: %s", e)
    except BaseException as e:
        record.update(status="failed", error=f"{type(e).__name__}: {e}",
                      traceback=traceback.format_exc(limit=20))
        raise
    finally:
        record["wall_s"] = time.perf_counter() - t0
        write_json(metrics_path, record)
    return record


def fit_scene(cfg: DictConfig, scene, run_dir: Path, device: torch.device, generator: torch.Generator):
    """Build the model, rasterizer, loss, strategy and optimiser from ``cfg`` and train on ``scene``.

    Returns (model, rasterizer, training statistics). Used for the main run and for capacity searches.
    """
    rasterizer = build(cfg.rasterizer)
    init_points = build(cfg.init)(scene, generator)
    model = build(cfg.model, init=init_points.to(device), n_frames=scene.n_frames).to(device)
    loss_fn = build(cfg.loss)
    strategy = build(cfg.strategy, extent=scene.extent)
    optim_factory = build(cfg.optim)

    def make_optimizer(m):
        return optim_factory(groups=m.param_groups(), extent=scene.extent)

    trainer = build(cfg.trainer)
    stats = trainer.fit(model, scene, rasterizer, loss_fn, make_optimizer, strategy, run_dir, generator, seed=cfg.seed)
    return model, rasterizer, stats


# Overrides that do not change a run's results; a re-run may add or change them (resume check above).
_NEUTRAL_OVERRIDES = ("skip_if_done", "threads", "trainer.progress", "trainer.log_every")


def _identity_overrides(overrides: list[str]) -> list[str]:
    """The overrides that identify a job: ``overrides`` without the :data:`_NEUTRAL_OVERRIDES` keys."""
    return [o for o in overrides if o.split("=", 1)[0].lstrip("+~") not in _NEUTRAL_OVERRIDES]


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    record = run(cfg)
    return record.get("metrics", {}).get("psnr")


if __name__ == "__main__":
    main()
