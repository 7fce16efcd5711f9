"""Entry point: ``python -m src.run [+experiment=NAME] [group=option ...] [key=value ...] [+ci=smoke]``.

Builds every component from its config group through :func:`src.utils.instantiate.build`, trains,
evaluates and writes the run record ``metrics.json`` (atomically, also when the run fails).
"""

from __future__ import annotations

from src.kernels.threads import configure_openmp

configure_openmp()  # before anything loads torch's OpenMP runtime (src/kernels/threads.py)

import errno
import logging
import math
import sys
import time
import traceback
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError

from src.data.base import DatasetError
from src.data.validate import validate_scene
from src.init.stage1 import check_second_stage_init, ensure_first_stage, ingredient_tag
from src.io.compressed import COMPRESSED_FILE
from src.io.ply import BAKED_PLY, scene_frames, write_baked_ply
from src.trainer.fit import fit_scene
from src.trainer.guard import DivergenceError, DivergenceGuard
from src.trainer.trainer import CheckpointError
from src.utils.hydra_cli import job_started, run_cli
from src.utils.instantiate import ConfigError, build, check_targets
from src.utils.interrupt import RunInterrupted, stop_on_signals
from src.utils.memory import peak_memory_mb
from src.utils.record import atomic_write_text, env_info, read_json, write_json
from src.utils.runlock import RunDirLocked, RunLock
from src.utils.seed import seed_everything
from src.utils.validate import ConfigValueError, validate_run_config

log = logging.getLogger("src.run")
REPO_ROOT = Path(__file__).resolve().parents[1]
if not OmegaConf.has_resolver("repo"):
    OmegaConf.register_new_resolver("repo", lambda: str(REPO_ROOT))
if not OmegaConf.has_resolver("basename"):
    OmegaConf.register_new_resolver("basename", lambda p: Path(str(p)).name)
if not OmegaConf.has_resolver("half"):  # narrow heads are half the width of the wide ones (B.2: 64 vs 128)
    OmegaConf.register_new_resolver("half", lambda w: max(8, int(w) // 2))


def if_at_most(n: int | None, limit: int, then, otherwise):
    """``then`` when ``n`` (e.g. the training view count; None = all views) is at most ``limit``, else
    ``otherwise``: settings that differ between the sparsest and denser view counts."""
    return then if n is not None and int(n) <= int(limit) else otherwise


if not OmegaConf.has_resolver("if_at_most"):
    OmegaConf.register_new_resolver("if_at_most", if_at_most)
if not OmegaConf.has_resolver("sparse_tag"):  # a first stage's ingredient in its cache directory's name
    OmegaConf.register_new_resolver("sparse_tag", ingredient_tag)
def times(base, factor) -> int:
    """``${times:BASE,FACTOR}``: BASE x FACTOR, rounded: a schedule scaled with its budget (``schedule.budget_scale``,
    conf/scale/). A factor that is not a positive number is refused naming ``schedule.budget_scale``."""
    try:
        x = float(factor)
    except (TypeError, ValueError):
        x = math.nan
    if not math.isfinite(x) or x <= 0:
        raise ValueError(f"schedule.budget_scale={factor!r}: expected a positive number")
    return round(float(base) * x)


if not OmegaConf.has_resolver("times"):
    OmegaConf.register_new_resolver("times", times)


def resolve_device(name: str) -> torch.device:
    """``auto`` -> cuda if available else cpu; otherwise the named device (``cpu``, ``cuda``, ``cuda:N``),
    which must exist here (:class:`ConfigValueError` naming ``device`` otherwise)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(str(name))
    except RuntimeError:
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ConfigValueError(f"device={name!r}: expected auto, cpu, cuda or cuda:N")
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ConfigValueError(f"device={name}: no CUDA GPU is visible to this torch "
                                   f"({torch.__version__}); use device=auto or device=cpu")
        if device.index is not None and device.index >= count:
            raise ConfigValueError(f"device={name}: only {count} CUDA GPU(s) visible (cuda:0 to cuda:{count - 1})")
    return device


def hydra_context() -> dict:
    """Group choices, overrides and output dir of the current Hydra job (empty outside Hydra)."""
    try:
        hc = HydraConfig.get()
    except ValueError:
        return {"choices": {}, "overrides": [], "output_dir": None}
    choices = {k: v for k, v in OmegaConf.to_container(hc.runtime.choices).items()
               if not k.startswith("hydra/") and v is not None}
    return {"choices": choices, "overrides": list(hc.overrides.task), "output_dir": hc.runtime.output_dir}


class RunDirError(ConfigError):
    """The run directory cannot be used: it holds another job, or it cannot be written (read-only, full)."""


#: Errors in what the user gave (config values, data files, checkpoints, run dirs): one line, no traceback.
INPUT_ERRORS = (ConfigError, ConfigValueError, DatasetError, CheckpointError, RunDirLocked)
#: OS errors that mean the run directory cannot be written (not a bug of the run).
_UNWRITABLE = (errno.EROFS, errno.ENOSPC, errno.EACCES, errno.EPERM, errno.EDQUOT, errno.ENOTDIR, errno.EEXIST)


def unwritable(e: BaseException, run_dir: Path) -> RunDirError | None:
    """A one-line :class:`RunDirError` for an OS error writing ``run_dir`` (read-only, full, no permission)."""
    if not isinstance(e, OSError) or e.errno not in _UNWRITABLE:
        return None
    where = e.filename or run_dir
    return RunDirError(f"{where}: cannot write the run directory {run_dir} ({e.strerror or e}); free space or "
                       "choose a writable place with hydra.run.dir=... (paths.output_root for new runs)")


def save_hydra_files(cfg: DictConfig, run_dir: Path) -> None:
    """Write ``<run>/.hydra/{config,hydra,overrides}.yaml`` (atomically) for the current Hydra job.

    Hydra's own copy is switched off (``hydra.output_subdir: null`` in conf/config.yaml) so that these
    files are written only by the process holding the run directory's lock: a refused second writer
    leaves the running job's files untouched.
    """
    try:
        hc = HydraConfig.get()
    except ValueError:
        return
    out = run_dir / ".hydra"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "config.yaml", OmegaConf.to_yaml(cfg))
    atomic_write_text(out / "hydra.yaml", OmegaConf.to_yaml(OmegaConf.create({"hydra": hc})))
    atomic_write_text(out / "overrides.yaml", OmegaConf.to_yaml(hc.overrides.task))


def run(cfg: DictConfig, run_dir: Path | None = None) -> dict:
    """Train and evaluate one configuration; returns the run record (also written to metrics.json).

    The run directory is locked for the whole run (:class:`src.utils.runlock.RunLock`): a second
    process writing to it is refused with :class:`RunDirLocked` before it changes anything there.
    """
    ctx = hydra_context()
    run_dir = Path(run_dir or ctx["output_dir"] or cfg.paths.output_dir)
    try:
        run_dir.mkdir(parents=True, exist_ok=True)
        lock = RunLock(run_dir).acquire()
    except OSError as e:
        raise unwritable(e, run_dir) or e from None
    try:
        with stop_on_signals():
            return _run_locked(cfg, run_dir, ctx)
    except InterpolationResolutionError as e:  # a value the config cannot resolve: one line naming the key
        raise ConfigValueError(f"{e.full_key}: {str(e).splitlines()[0]}") from None  # not its key / type lines
    except OSError as e:  # e.g. the disk filled up while writing a checkpoint: the last good one stays
        raise unwritable(e, run_dir) or e from None
    finally:
        lock.release()


def _run_locked(cfg: DictConfig, run_dir: Path, ctx: dict) -> dict:
    """:func:`run`'s body, with the run directory's lock held: check the directory, then train and record."""
    metrics_path = run_dir / "metrics.json"
    previous = read_json(metrics_path)
    check_same_job(previous, ctx, run_dir)
    fresh = not cfg.trainer.get("resume", True)  # trainer.resume=false: train again from scratch
    if cfg.get("skip_if_done", True) and not fresh and previous and previous.get("status") == "ok":
        log.info("%s already says status ok: skipping (set skip_if_done=false to re-run)", metrics_path)
        return previous
    # A run killed (SIGKILL) inside an atomic write leaves its temporary file (.NAME.XXXX.tmp, see
    # src/utils/record.py); the run dir belongs to this job alone, so drop such leftovers.
    for stale in run_dir.glob(".*.tmp"):
        stale.unlink(missing_ok=True)
    device = resolve_device(cfg.device)  # a GPU that is not there: refused before anything is written
    record = new_record(cfg, ctx, run_dir, device)
    if ctx["output_dir"] is not None:
        save_hydra_files(cfg, run_dir)
    # Written now with status "running" (never "ok" before the end): a killed run leaves this record,
    # so tables list it as not finished and a re-run can check it is the same job (above).
    write_json(metrics_path, record)
    t0 = time.perf_counter()
    try:
        train_and_evaluate(cfg, run_dir, device, record)
    except DivergenceError as e:
        reason = str(e) if str(e).startswith("collapse:") else f"divergence: {e}"
        record.update(status="failed", reason=reason, error=str(e))
        log.error("run diverged: %s", e)
    except BaseException as e:
        raise record_failure(record, e, run_dir) from None
    finally:
        record["wall_s"] = time.perf_counter() - t0
        try:
            write_json(metrics_path, record)
        except OSError as e:  # a full or read-only disk: the record from the start of the run stays
            log.error("could not update %s (%s)", metrics_path, e)
    return record


def check_same_job(previous: dict | None, ctx: dict, run_dir: Path) -> None:
    """Refuse a run dir whose record holds another job's overrides (:class:`RunDirError`, one line).

    Resume safety (sweeps/README.md, "Resume"): a sweep re-run with changed parameters renumbers its
    jobs, and skipping an "ok" record or resuming a checkpoint of another configuration would silently
    attribute results to the wrong config.
    """
    if not previous or ctx["output_dir"] is None or previous.get("overrides") is None:
        return
    before, now = _identity_overrides(previous["overrides"]), _identity_overrides(ctx["overrides"])
    if before != now:
        raise RunDirError(
            f"{run_dir} holds another run (overrides {before}); this job has {now}. Re-use a run/sweep "
            "dir only with the same command; to extend a sweep use a new hydra.sweep.dir and pass both "
            "directories to src.tables.")


def new_record(cfg: DictConfig, ctx: dict, run_dir: Path, device: torch.device) -> dict:
    """The run record as written at the start of a run (``status: running``; keys of metrics.json, see
    :mod:`src.utils.record`)."""
    return {
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


def record_failure(record: dict, e: BaseException, run_dir: Path) -> BaseException:
    """Fill ``record`` for a run that stopped with ``e``; returns the exception to raise.

    Input errors (and a run dir that cannot be written) say ``invalid input: <line>``; a signal says
    ``interrupted`` and where the checkpoint is; anything else keeps its traceback in the record.
    """
    bad_dir = unwritable(e, run_dir)
    if bad_dir is not None:
        e = bad_dir
    if isinstance(e, INPUT_ERRORS):
        record.update(status="failed", reason=f"invalid input: {e}", error=f"{type(e).__name__}: {e}")
    elif isinstance(e, RunInterrupted):
        e.reason = interruption_reason(e, run_dir / "checkpoint.pt")
        record.update(status="interrupted", reason=e.reason, error=str(e),
                      interrupted={"signal": e.name, "checkpoint_iteration": e.checkpoint_iteration})
    else:
        record.update(status="failed", reason=f"{type(e).__name__}: {str(e)[:300]}",
                      error=f"{type(e).__name__}: {e}", traceback=traceback.format_exc(limit=20))
    return e


def train_and_evaluate(cfg: DictConfig, run_dir: Path, device: torch.device, record: dict) -> None:
    """Load the scene, run the first stage / capacity search if configured, train, evaluate, write the
    splats; fills ``record`` (keys, views, metrics, curve, ...) and sets ``status: ok``."""
    check_second_stage_init(cfg, (record.get("choices") or {}).get("init"))  # before check_targets names run_dir
    check_targets(cfg)  # every _target_ at every depth, before anything is built
    validate_run_config(cfg)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    generator = seed_everything(cfg.seed)
    scene = load_scene(cfg, device)
    record["keys"]["scene"] = scene.name
    record["views"] = scene.view_ids
    record["image_size"] = scene.image_size
    stage1 = ensure_first_stage(cfg, scene, device)  # two-stage protocol, stage1.auto
    if stage1 is not None:
        record["stage1"] = stage1
        generator = seed_everything(cfg.seed)  # the same stream whether stage 1 was trained or read
    capacity = build(cfg.capacity) if cfg.get("capacity") else None
    if capacity is not None and capacity.enabled:
        t_search = time.perf_counter()
        cfg, record["capacity"] = capacity.choose(cfg, scene, run_dir / "capacity", device)
        record["capacity"]["search_s"] = time.perf_counter() - t_search
        record["keys"].update(record["capacity"]["chosen"])
    model, rasterizer, train_stats = fit_scene(cfg, scene, run_dir, device, generator)
    # compress=...: write the compressed splat file and evaluate what it decodes to (LightGaussian)
    compression = build(cfg.compress).apply(model, rasterizer, scene, run_dir) if cfg.get("compress") else {}
    evaluate_into(record, cfg, model, rasterizer, scene, run_dir, device)
    record["metrics"].update({"train_s": train_stats["train_s"], "iter_ms": train_stats["iter_ms"],
                              **{f"iter_{k}": v for k, v in train_stats["timing"].items()}, **compression})
    if stage1 is not None:  # the first stage is part of this method's training cost
        record["metrics"]["stage1_train_s"] = stage1["train_s"]
    if "capacity" in record:  # so is the capacity search
        record["metrics"]["capacity_search_s"] = record["capacity"]["search_s"]
    if train_stats.get("curve"):  # learning curve: held-out PSNR against iteration and training time
        record["curve"] = train_stats["curve"]
        record["curve_split"] = train_stats.get("curve_split")
    record["rasterizer"] = getattr(rasterizer, "name", type(rasterizer).__name__)
    write_baked_ply(model, run_dir, frames=scene_frames(scene))
    if cfg.get("mesh"):  # mesh=poisson (SuGaR): <run>/mesh.ply of the baked splats, or why none was written
        centres = torch.stack([v.camera.center for v in scene.train])  # [C, 3] training cameras
        record["mesh"] = build(cfg.mesh).write(model.bake(), centres, run_dir)
    if (run_dir / BAKED_PLY).is_file():  # the splat set's size on disk in the 3DGS PLY layout (MiB)
        record["metrics"]["size_mb_ply"] = (run_dir / BAKED_PLY).stat().st_size / 2**20
    record["status"] = "ok"
    log.info("test PSNR %.2f dB, SSIM %.4f, %d splats, %.1f s", record["metrics"]["psnr"],
             record["metrics"]["ssim"], model.n_splats, record["metrics"]["train_s"])


def load_scene(cfg: DictConfig, device: torch.device):
    """The configured scene, validated and checked against the experiment, on ``device``."""
    scene = build(cfg.dataset).load()
    validate_scene(scene, str(cfg.dataset.root))
    check_combination(cfg, scene)
    return scene.to(device)


def evaluate_into(record: dict, cfg: DictConfig, model, rasterizer, scene, run_dir: Path,
                  device: torch.device) -> None:
    """Test-view metrics, renders and the final divergence checks into ``record`` (``metrics``, ``per_view``)."""
    evaluator = build(cfg.eval)
    ev = evaluator.evaluate(model, rasterizer, scene, run_dir)
    if cfg.trainer.get("tensorboard", False):
        evaluator.log_images(run_dir, model, rasterizer, scene, step=int(cfg.trainer.iterations))
    guard = DivergenceGuard(**OmegaConf.to_container(cfg.trainer.get("guard") or {}, resolve=True))
    ev["background_psnr"] = guard.check_final(model, rasterizer, scene, ev["psnr"], int(cfg.trainer.iterations))
    record["per_view"] = ev.pop("per_view_test")
    per_frame = ev.pop("per_frame", None)
    if per_frame is not None:
        record["per_frame"] = per_frame
    unavailable = ev.pop("unavailable_metrics", None)
    if unavailable:
        record["unavailable_metrics"] = unavailable  # e.g. LPIPS without user-supplied backbone weights
    record["metrics"] = {"psnr": ev.pop("psnr"), "ssim": ev.pop("ssim"), "n_splats": model.n_splats,
                         "n_params": model.n_params(), "peak_mem_mb": peak_memory_mb(device), **ev}


def interruption_reason(e: RunInterrupted, ckpt: Path) -> str:
    """``interrupted by SIGTERM; checkpoint at iteration N (...)``: what the record says of a stopped run."""
    done = e.checkpoint_iteration
    if done is None and ckpt.is_file():
        try:
            done = int(torch.load(ckpt, map_location="cpu", weights_only=True)["iteration"]) + 1
        except Exception:
            done = None
    where = f"checkpoint at iteration {done} ({ckpt})" if done is not None else "no checkpoint in this run dir"
    return f"interrupted by {e.name}; {where}; re-run the same command to resume"


# Overrides that do not change a run's results; a re-run may add or change them (resume check above).
_NEUTRAL_OVERRIDES = ("skip_if_done", "threads", "trainer.progress", "trainer.log_every", "trainer.resume")


def _identity_overrides(overrides: list[str]) -> list[str]:
    """The overrides that identify a job: ``overrides`` without the :data:`_NEUTRAL_OVERRIDES` keys."""
    return [o for o in overrides if o.split("=", 1)[0].lstrip("+~") not in _NEUTRAL_OVERRIDES]


#: Model classes that always model motion (SplatFields does when ``model.network.dynamic`` is true).
DYNAMIC_MODELS = ("src.models.deformable.DeformableGaussianModel", "src.models.gaussians4d.HexPlaneGaussianModel")


def check_combination(cfg: DictConfig, scene) -> None:
    """Refuse, in one line, an experiment that models motion on a scene that has none."""
    dynamic_model = bool(OmegaConf.select(cfg, "model.network.dynamic", default=False)) or str(
        OmegaConf.select(cfg, "model._target_", default="")) in DYNAMIC_MODELS
    if dynamic_model and not scene.is_dynamic:
        raise ConfigError(
            f"experiment {cfg.get('experiment_name', 'default')!r} ({cfg.method}) models motion, but dataset "
            f"{scene.name!r} ({cfg.dataset._target_.rsplit('.', 1)[-1]}) is a static scene with one frame: use a "
            "dynamic reader (dataset=blender_mv | owlii | dnerf | nerfies) or a static experiment")


def print_summary(record: dict, run_dir: Path) -> None:
    """The end-of-run summary on stdout: metrics, time, splats, and where everything was written."""
    m = record.get("metrics", {})
    if record.get("status") != "ok":
        print(f"\nrun failed: {record.get('reason') or record.get('error')}\n  record: {run_dir / 'metrics.json'}")
        return
    lines = [
        "",
        f"{record.get('method')} on {record['keys'].get('scene')} ({record['keys'].get('n_views')} views): "
        f"test PSNR {m.get('psnr', float('nan')):.2f} dB, SSIM {m.get('ssim', float('nan')):.4f}, "
        f"{m.get('n_splats')} splats, trained in {m.get('train_s', float('nan')):.0f} s",
        f"  metrics   {run_dir / 'metrics.json'}",
        f"  renders   {run_dir / 'renders' / 'test'}",
        f"  splats    {run_dir / 'splats.ply'}",
        *([f"  compressed {run_dir / COMPRESSED_FILE} ({m['size_mb']:.3f} MiB; "
           f"the PLY {m.get('size_mb_ply', float('nan')):.3f} MiB)"] if "size_mb" in m else []),
        f"  logs      tensorboard --logdir {run_dir / 'tb'}",
        f"  view      python -m src.view {run_dir}",
    ]
    print("\n".join(lines))


def _run_mode() -> RunMode:
    try:
        return HydraConfig.get().mode
    except ValueError:
        return RunMode.RUN


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    """The CLI: a single run exits 2 on invalid input and 1 if the run failed (diverged or collapsed).

    In a sweep (``--multirun``) a failed run is recorded and the sweep goes on.
    """
    job_started()  # Hydra composed the config: stderr is no longer held (src/utils/hydra_cli.py)
    single = _run_mode() == RunMode.RUN
    try:
        record = run(cfg)
    except INPUT_ERRORS as e:
        if not single:
            raise
        print(f"error: {e}", file=sys.stderr)  # one line, no traceback (the record holds the error too)
        sys.exit(2)
    except RunInterrupted as e:  # stops a sweep too; the record says where the checkpoint is
        print(f"\n{getattr(e, 'reason', e)}", file=sys.stderr)
        sys.exit(128 + e.signum)
    if single:
        print_summary(record, Path(record.get("run_dir", ".")))
        if record.get("status") != "ok":
            sys.exit(1)
    return record.get("metrics", {}).get("psnr")


if __name__ == "__main__":
    run_cli(main)
