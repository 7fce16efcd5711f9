"""Tables (and charts) from sweep results: ``python -m src.tables SWEEP_DIR [SWEEP_DIR...]``.

Reads ``SWEEP_DIR/multirun.yaml`` (its ``report:`` block) and every ``SWEEP_DIR/**/metrics.json`` (or the runs
of a run archive ``runs.jsonl.gz`` given in place of a directory), prints the tables, and optionally writes
``OUT/table.{md,tex,csv}``, ``OUT/runs.jsonl.gz`` (every run read: the table can be rebuilt or extended from it,
:mod:`src.reporting.archive`), ``chart.{png,svg}`` (speed against accuracy) and ``curves.{png,svg}`` (learning
curves, when the records carry a ``curve``).
A bare ``--out`` writes to ``sweeps/results/<sweep name>/`` (the name of the sweep's config file,
read from its ``multirun.yaml``), the place where the current result of each sweep is kept.
Conventions and the record contract: :mod:`src.reporting`.

Exit codes: 0 success; 2 bad usage or nothing to tabulate or chart (a sweep directory missing,
without any metrics.json, or with no readable record; an output folder that cannot be written or that
another ``src.tables`` is writing into: one writer per folder), with one line on stderr.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from src.reporting import load, make_tables, resolve_spec
from src.reporting.aggregate import ReportSpec, build_report
from src.reporting.archive import is_archive, write_archive
from src.reporting.collect import Collection, find_metrics_files
from src.reporting.render import FORMATS, render
from src.utils.record import OneLineParser, OutputBusy, atomic_write_text, cli_error, os_error_line, output_lock

if TYPE_CHECKING:
    from src.reporting.chart import ChartData

__all__ = ["main", "make_tables"]


RESULTS_ROOT = Path(__file__).resolve().parents[1] / "sweeps" / "results"
_DEFAULT_OUT = Path("<sweeps/results/SWEEP>")  # sentinel of a bare --out


def sweep_name(sweep_dir: Path) -> str | None:
    """The sweep's config name (``hydra.job.config_name`` in ``SWEEP_DIR/multirun.yaml``), or None."""
    try:
        data = yaml.safe_load((sweep_dir / "multirun.yaml").read_text())
        name = data["hydra"]["job"]["config_name"]
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return None
    return str(name) if name else None


def default_out(sweep_dirs: Sequence[Path]) -> Path | None:
    """``sweeps/results/<name>`` when every sweep directory names the same sweep, else None."""
    names = {sweep_name(d) for d in sweep_dirs}
    if len(names) != 1 or None in names:
        return None
    return RESULTS_ROOT / str(names.pop())


def _csv_list(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Command-line arguments (see ``--help``)."""
    parser = OneLineParser(
        prog="python -m src.tables",
        description="Aggregate metrics.json files of Hydra sweeps into paper-style tables.",
    )
    parser.add_argument("sweep_dirs", nargs="+", type=Path, metavar="SWEEP_DIR",
                        help="a sweep directory (its **/metrics.json), or a run archive runs.jsonl.gz that an earlier "
                        "--out wrote (src.reporting.archive)")
    parser.add_argument("--format", choices=FORMATS, default="md", help="output format (default: md)")
    parser.add_argument(
        "--out",
        type=Path,
        nargs="?",
        const=_DEFAULT_OUT,
        help="also write OUT/table.<format>, OUT/runs.jsonl.gz (every run read) and the charts there; bare: "
        "sweeps/results/<sweep name>/",
    )
    parser.add_argument("--rows", type=_csv_list, help="row keys, comma-separated dotted paths")
    parser.add_argument("--cols", type=_csv_list, help="column keys; '--cols=' → one column per metric")
    parser.add_argument("--metrics", type=_csv_list, help="metrics, comma-separated (one table each)")
    parser.add_argument(
        "--quoted",
        nargs="?",
        const="auto",
        metavar="TAB",
        help="append the paper's rows for systems not run: a table (C.1 … C.6) or, bare, chosen by dataset",
    )
    parser.add_argument("--no-quoted", action="store_true", help="drop the report block's quoted paper rows")
    parser.add_argument(
        "--chart",
        action="store_true",
        help="write chart.png/.svg (speed against accuracy) and, with curves in the records, curves.png/.svg",
    )
    parser.add_argument(
        "--leaderboard",
        action="store_true",
        help="rank every method at its own budget, chosen on validation views: print it, and with --out write "
        "leaderboard.md/.json, leaderboard_curves.png/.svg and runs.jsonl.gz (src.reporting.leaderboard)",
    )
    parser.add_argument(
        "--reference",
        metavar="EXPERIMENT",
        help="with --leaderboard: the method whose mean training time sets the equal-time column "
        "(default: splatfields3d_mip)",
    )
    return parser.parse_args(argv)


def _dotted_keys(data: Any, prefix: str = "", depth: int = 3) -> set[str]:
    """Dotted paths of ``data``'s nested mappings, ``depth`` levels down (what --rows / --cols may name)."""
    out: set[str] = set()
    if isinstance(data, dict) and depth > 0:
        for k, v in data.items():
            path = f"{prefix}.{k}" if prefix else str(k)
            if not isinstance(v, dict | list):
                out.add(path)
            out |= _dotted_keys(v, path, depth - 1)
    return out


def unknown_keys(records: Sequence, spec) -> str | None:
    """A one-line message naming the row / column keys and metrics no record has, with the valid choices."""
    keys: set[str] = set()
    for r in records:
        keys |= _dotted_keys(dict(r.data))
    metrics = sorted({k.split(".", 1)[1] for k in keys if k.startswith("metrics.")})
    for name in ("rows", "cols"):
        missing = [k for k in getattr(spec, name) if k not in keys]
        if missing:
            choices = sorted(k for k in keys if k.split(".", 1)[0] in ("method", "experiment", "keys", "choices"))
            return f"--{name}: no run has {', '.join(missing)}; choose from: {', '.join(choices)}"
    missing = [m for m in spec.metrics if m not in metrics]
    if missing and len(missing) == len(spec.metrics):
        return f"--metrics: no run has {', '.join(missing)}; choose from: {', '.join(metrics)}"
    return None


def check_sweep_dirs(sweep_dirs: Sequence[Path]) -> str | None:
    """A one-line message for the first sweep directory that is missing, a file, or holds no metrics.json (a run
    archive, ``runs.jsonl.gz``, is checked when it is read: :func:`unreadable_archive`)."""
    for sweep_dir in sweep_dirs:
        if is_archive(sweep_dir):
            continue
        if not sweep_dir.exists():
            return f"{sweep_dir}: no such directory; expected a sweep directory (holding **/metrics.json)"
        if not sweep_dir.is_dir():
            return f"{sweep_dir}: is a file; expected a sweep directory (holding **/metrics.json)"
        if not find_metrics_files(sweep_dir):
            return f"no metrics.json under {sweep_dir} (empty or unfinished sweep?); expected run directories"
    return None


def unreadable_archive(collection: Collection) -> str | None:
    """A one-line message for the first run archive that could not be read at all, or None."""
    problem = next((p for p in collection.problems if p.whole_file), None)
    if problem is None:
        return None
    return f"{problem}; expected a run archive written by src.tables --out (gzip of JSON lines)"


def unreadable(collection: Collection) -> str:
    """The message when none of the records could be read: the count and the first file's problem."""
    first = collection.problems[0] if collection.problems else "no problem recorded"
    what = ("the only metrics.json could not be read" if collection.n_files == 1
            else f"none of the {collection.n_files} metrics.json files could be read, first")
    return (f"{what}: {first}; expected run records: JSON objects with 'status' "
            "(and 'method', 'keys', 'metrics' when ok)")


def write_outputs(args: argparse.Namespace, text: str, collection: Collection, spec: ReportSpec,
                  chart: ChartData | None) -> None:
    """Print ``text``; write ``table.<format>`` into ``args.out`` and the charts, holding the folder's lock.

    Raises:
        OutputBusy: another process writes into the output folder (nothing was printed or written).
        OSError: a file cannot be written.
    """
    out_dir = args.out or (args.sweep_dirs[0] if chart is not None else None)
    with output_lock(out_dir, "choose another --out") if out_dir is not None else nullcontext():
        print(text, end="")
        if args.out is not None:
            table = args.out / f"table.{args.format}"
            atomic_write_text(table, text)
            for path in (table, write_archive(collection.records, args.out)):
                print(f"wrote {path}", file=sys.stderr)
        if chart is not None:
            from src.reporting.chart import draw_chart, make_curves

            paths = draw_chart(chart, out_dir) + make_curves(collection.records, spec, out_dir)
            for path in paths:
                print(f"wrote {path}")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit code."""
    args = parse_args(argv)
    if args.reference is not None and not args.leaderboard:
        return cli_error("--reference needs --leaderboard")
    problem = check_sweep_dirs(args.sweep_dirs)
    if problem:
        return cli_error(problem)
    collection = load(args.sweep_dirs)
    problem = unreadable_archive(collection)
    if problem:
        return cli_error(problem)
    if args.out == _DEFAULT_OUT:
        args.out = default_out(args.sweep_dirs)
        if args.out is None:
            return cli_error("a bare --out needs sweep directories of one named sweep (multirun.yaml); pass --out DIR")
    if args.chart and args.out is None and is_archive(args.sweep_dirs[0]):
        return cli_error(f"--chart: {args.sweep_dirs[0]} is a run archive, and charts without --out are written into "
                         "the first sweep directory; pass --out DIR")

    if not collection.records:
        return cli_error(unreadable(collection))
    for skipped in collection.problems:
        print(f"skipped {skipped}", file=sys.stderr)
    if args.leaderboard:
        from src.reporting.leaderboard import leaderboard_cli

        return leaderboard_cli(collection, args.out, args.reference)
    try:
        spec = resolve_spec(None, collection).with_overrides(
            rows=args.rows, cols=args.cols, metrics=args.metrics, quoted=args.quoted
        )
        if args.no_quoted:
            spec = replace(spec, quoted=None)
    except ValueError as exc:
        return cli_error(f"bad report block: {exc}")
    unknown = unknown_keys(collection.records, spec)
    if unknown:
        return cli_error(unknown)

    text = render(build_report(collection.records, spec, collection.problems), args.format)
    chart = None
    if args.chart:
        from src.reporting.chart import chart_data, drawable_qualities  # matplotlib only when charting

        chart = chart_data(collection.records, spec)
        try:
            drawable_qualities(chart)
        except ValueError as exc:
            return cli_error(f"--chart: {exc}")
    try:
        write_outputs(args, text, collection, spec, chart)
    except OutputBusy as exc:
        return cli_error(str(exc))
    except OSError as exc:
        return cli_error(f"cannot write the output: {os_error_line(exc)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
