"""``python -m src.prune RUN_DIR [RUN_DIR ...] [--keep 0.5,0.25,0.1] [--max-loss-db 0.2] [--write]``

Shrink a finished run's baked splat set to what the scene needs and state the PSNR it costs
(LightGaussian-style significance pruning, no fine-tuning).

Conventions: the run's ``splats.ply`` is its baked model (activated splats, DC colours: what the
evaluator scores as ``baked_psnr``); significance is the blending weight alpha·T summed over the run's
TRAINING views times the normalised volume^0.1 (``src.strategy.significance``); PSNR is measured on
renders composited on the scene background, 8-bit rounded when the run's ``eval.quantise`` is
on, as the evaluator does. The keep fraction is chosen on
training-view PSNR (the smallest model whose training PSNR drops by at most ``--max-loss-db``), never
on test views; the test-view PSNR of every fraction is reported next to it.

Writes ``<run>/pruning.json`` (atomically) and, with ``--write``, ``<run>/splats_pruned.ply`` (the
chosen set). Static scenes only.
"""

from __future__ import annotations

from src.kernels.threads import configure_openmp

configure_openmp()  # before anything loads torch's OpenMP runtime (src/kernels/threads.py)

import argparse
import math
from pathlib import Path

import torch
from omegaconf import OmegaConf

from src.core.splats import Splats
from src.data.base import View
from src.eval.evaluator import views_psnr
from src.io.ply import read_ply, write_ply
from src.strategy.significance import splat_set_significance
from src.utils.instantiate import ConfigError, build
from src.utils.record import USAGE_ERROR, OneLineParser, cli_error, os_error_line, write_json

DEFAULT_KEEP = (0.5, 0.25, 0.1)


def prune_run(run_dir: Path, keeps: list[float], max_loss_db: float, write: bool = False,
              volume_power: float = 0.1) -> dict:
    """Significance-prune one run's ``splats.ply`` at each keep fraction; returns the ``pruning.json`` record."""
    import src.run  # noqa: F401 - registers the resolvers the saved config uses

    if not run_dir.is_dir():
        found = "is a file" if run_dir.exists() else "does not exist"
        raise FileNotFoundError(f"{run_dir}: {found}; expected a finished run directory of src.run")
    cfg_path, ply_path = run_dir / ".hydra" / "config.yaml", run_dir / "splats.ply"
    for p in (cfg_path, ply_path):
        if not p.is_file():
            raise FileNotFoundError(f"{p}: missing (is {run_dir} a finished run directory of src.run?)")
    try:
        cfg = OmegaConf.load(cfg_path)
        missing = [k for k in ("dataset", "rasterizer") if OmegaConf.select(cfg, k) is None]
    except Exception as e:  # yaml or OmegaConf errors: name the file, one line
        raise ValueError(f"{cfg_path}: unreadable run config ({type(e).__name__}: "
                         f"{str(e).splitlines()[0] if str(e) else ''})") from e
    if missing:
        raise ValueError(f"{cfg_path}: run config lacks {', '.join(missing)} (not written by src.run?)")
    splats = read_ply(ply_path).splats  # a malformed or non-finite file fails before the scene loads
    try:
        scene = build(cfg.dataset).load()
        rasterizer = build(cfg.rasterizer)
    except ConfigError as e:
        raise ValueError(f"{cfg_path}: {e}") from e
    if scene.is_dynamic:
        raise ValueError(f"{run_dir}: pruning a baked splat set is defined for static scenes only")
    bg = scene.background
    q = bool(OmegaConf.select(cfg, "eval.quantise", default=True))  # the run's evaluation protocol

    def psnr_of(s: Splats, views: list[View]) -> float:
        return views_psnr(lambda _cam: s, rasterizer, views, bg, q)

    base = {"keep": 1.0, "n_splats": splats.n, "psnr_train": psnr_of(splats, scene.train),
            "psnr": psnr_of(splats, scene.test)}
    significance = splat_set_significance(splats, rasterizer, scene.train, volume_power)  # [N], training views only
    order = torch.argsort(significance, descending=True, stable=True)
    rows, chosen, kept = [base], base, splats
    for keep in sorted(keeps, reverse=True):
        sub = splats.index(order[: max(1, round(keep * splats.n))])
        row = {"keep": keep, "n_splats": sub.n, "psnr_train": psnr_of(sub, scene.train),
               "psnr": psnr_of(sub, scene.test)}
        row["train_loss_db"] = base["psnr_train"] - row["psnr_train"]
        row["test_loss_db"] = base["psnr"] - row["psnr"]
        rows.append(row)
        if row["train_loss_db"] <= max_loss_db and row["n_splats"] < chosen["n_splats"]:
            chosen, kept = row, sub
    record = {"run_dir": str(run_dir), "scene": scene.name, "max_loss_db": max_loss_db,
              "selected_on": "training views", "rows": rows, "chosen": chosen}
    write_json(run_dir / "pruning.json", record)
    if write:
        write_ply(run_dir / "splats_pruned.ply", kept)
    return record


def keep_fractions(text: str) -> list[float]:
    """``--keep``: comma-separated fractions in (0, 1)."""
    try:
        keeps = [float(k) for k in text.split(",") if k.strip()]
    except ValueError:
        keeps = []
    if not keeps or not all(0.0 < k < 1.0 for k in keeps):
        raise argparse.ArgumentTypeError(f"{text!r}: expected comma-separated fractions in (0, 1), e.g. 0.5,0.25")
    return keeps


def non_negative(text: str) -> float:
    """A finite number of 0 or more (``--max-loss-db``, ``--volume-power``)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0.0):
        raise argparse.ArgumentTypeError(f"{text!r}: expected a finite number of 0 or more")
    return value


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line arguments (see ``--help``); a bad one exits with one line and code 2."""
    ap = OneLineParser(prog="python -m src.prune", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run directories (with splats.ply, .hydra/)")
    ap.add_argument("--keep", type=keep_fractions, default=list(DEFAULT_KEEP),
                    help="fractions of splats to keep, comma-separated (default: 0.5,0.25,0.1)")
    ap.add_argument("--max-loss-db", type=non_negative, default=0.2,
                    help="largest training-view PSNR loss (dB) the chosen model may cost")
    ap.add_argument("--write", action="store_true", help="also write the chosen set as splats_pruned.ply")
    ap.add_argument("--volume-power", type=non_negative, default=0.1,
                    help="exponent of the volume term of the significance (LightGaussian: 0.1)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Prune each run; exit code 0, or 2 if a run could not be used (one line naming its file on stderr)."""
    args = parse_args(argv)
    print(f"{'run':<40} {'keep':>5} {'splats':>7} {'train dB':>9} {'test dB':>8} {'test loss':>9}")
    failed = 0
    for run in args.runs:
        try:
            rec = prune_run(run, args.keep, args.max_loss_db, args.write, args.volume_power)
        except ValueError as e:
            failed += cli_error(str(e))
            continue
        except OSError as e:
            failed += cli_error(os_error_line(e))
            continue
        for r in rec["rows"]:
            mark = " <- chosen" if r is rec["chosen"] else ""
            print(f"{'/'.join(run.parts[-3:])[-40:]:<40} {r['keep']:>5.2f} {r['n_splats']:>7} {r['psnr_train']:>9.2f} "
                  f"{r['psnr']:>8.2f} {r.get('test_loss_db', 0.0):>9.2f}{mark}")
    return USAGE_ERROR if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
