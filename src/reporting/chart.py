"""Charts of sweep results: speed against accuracy, and learning curves.

``chart.{png,svg}`` (:func:`make_chart`): test quality (PSNR; SSIM in a second row when recorded)
against training time on a log axis, one panel per scene. One point per method and table column
(e.g. view count): the mean over the ``ok`` runs (seeds) with sample-std error bars on both axes.
Methods differ by marker (and colour when there is one column); columns differ by colour, with a
second legend, and a method's points are joined in column order. Failed runs are marked with a red
✕ on the panel's bottom edge at their training time, and counted in the method's legend entry. The
Pareto front of each panel (best quality for less time) is a dashed staircase.

``curves.{png,svg}`` (:func:`make_curves`): held-out PSNR against wall time for records whose
``metrics.json`` has a ``curve`` entry (a list of ``{"iteration": int, "wall_s": float, "psnr":
float}``); one panel per scene, one line per run, styled like the points of the first chart.

The same chart can be drawn from a ``table.md`` that :mod:`src.tables` wrote, when it holds a time
table (``train_s``) beside the quality tables (:func:`chart_from_table_md`,
``python -m src.reporting.chart --from-table TABLE.md``), for sweeps whose run directories are
not at hand. Uses matplotlib's object API with the Agg canvas, so no global backend is changed.
"""

from __future__ import annotations

import io
import math
import re
import statistics
import sys
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import EngFormatter, LogLocator, NullFormatter

from src.reporting.aggregate import ReportSpec, column_label, dedupe
from src.reporting.collect import RunRecord
from src.utils.record import OneLineParser, OutputBusy, atomic_write_bytes, cli_error, os_error_line, output_lock

QUALITIES = ("psnr", "ssim")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "h", "<", ">")
ALL_RUNS = "all runs"  # panel title when the records carry no scene
TIME_LABEL = "training time [s] (log; incl. first stage and capacity search)"
FAILED_COLOUR = "tab:red"


def _train_time(record: RunRecord) -> float | None:
    """Training time including a 3DGS first stage (two-stage protocol, ``stage1_train_s``) and a
    capacity search (``capacity_search_s``)."""
    t = record.metric("train_s")
    return (
        None
        if t is None
        else t + (record.metric("stage1_train_s") or 0.0) + (record.metric("capacity_search_s") or 0.0)
    )


@dataclass(frozen=True)
class Point:
    """Mean ± sample std of one (scene, method, column) group (std is 0 for a single run).

    Attributes:
        row: the method label (the report's row keys other than the scene).
        col: the column label (the report's column keys other than the scene; "" when none).
        panel: the scene ("" when the records carry none).
    """

    row: str
    col: str
    x: float
    x_err: float
    y: float
    y_err: float
    n: int
    panel: str = ""


@dataclass
class ChartData:
    """Everything one speed-against-accuracy figure shows, independent of where it was read from.

    Attributes:
        points: quality name → its points (one row of panels per quality with points).
        higher: quality name → whether higher is better.
        failed: method label → (failed runs, all runs), for the legend.
        failed_x: (panel, method, training time or None) per failed run.
        title, x_label: figure title and x-axis label.
    """

    points: dict[str, list[Point]]
    higher: dict[str, bool]
    failed: dict[str, tuple[int, int]] = field(default_factory=dict)
    failed_x: list[tuple[str, str, float | None]] = field(default_factory=list)
    title: str = ""
    x_label: str = TIME_LABEL


def _std(values: Sequence[float]) -> float:
    return statistics.stdev(values) if len(values) >= 2 else 0.0


def _is_scene(path: str) -> bool:
    return path.rsplit(".", 1)[-1] == "scene"


def _labels(record: RunRecord, spec: ReportSpec) -> tuple[str, str, str] | None:
    """(panel, method, column) of a record; None when a report key is missing."""
    try:
        rows = [(p, record.get(p)) for p in spec.rows]
        cols = [(p, record.get(p)) for p in spec.cols]
    except KeyError:
        return None  # reported by the table builder
    try:
        scene = str(record.get("keys.scene"))
    except KeyError:
        scene = ""
    method = " / ".join(
        str(v) if p.rsplit(".", 1)[-1] in ("method", "experiment") else f"{p.rsplit('.', 1)[-1]}={v}"
        for p, v in rows
        if not _is_scene(p)
    ) or str(record.data.get("method", ""))
    keep = [(p, v) for p, v in cols if not _is_scene(p)]
    col = column_label([p for p, _ in keep], tuple(v for _, v in keep)) if keep else ""
    return scene, method, col


def chart_points(records: Iterable[RunRecord], spec: ReportSpec, quality: str,
                 cost: Callable[[RunRecord], float | None] = _train_time) -> list[Point]:  # fmt: skip
    """Points of one quality: ``ok`` runs grouped by (scene, method, column); runs lacking x or y skipped."""
    groups: dict[tuple[str, str, str], list[tuple[float, float]]] = defaultdict(list)
    for record in records:
        labels = _labels(record, spec) if record.status == "ok" else None
        if labels is None:
            continue
        x, y = cost(record), record.metric(quality)
        if x is not None and y is not None and x > 0:
            groups[labels].append((x, y))
    points = []
    for (panel, row, col), pairs in sorted(groups.items()):
        xs, ys = [p[0] for p in pairs], [p[1] for p in pairs]
        points.append(Point(row, col, statistics.fmean(xs), _std(xs), statistics.fmean(ys), _std(ys),
                            len(pairs), panel))  # fmt: skip
    return points


def chart_data(records: Iterable[RunRecord], spec: ReportSpec) -> ChartData:
    """Collect the points and failed runs of :func:`make_chart` from run records."""
    records, _ = dedupe(records)
    data = ChartData(
        points={q: chart_points(records, spec, q) for q in QUALITIES},
        higher={q: spec.is_higher_better(q) for q in QUALITIES},
        title=spec.title,
    )
    totals: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for record in records:
        labels = _labels(record, spec)
        if labels is None or record.status not in ("ok", "failed"):
            continue
        panel, method, _ = labels
        totals[method][1] += 1
        if record.status == "failed":
            totals[method][0] += 1
            data.failed_x.append((panel, method, _train_time(record)))
    data.failed = {m: (f, n) for m, (f, n) in totals.items()}
    return data


def pareto_front(
    points: Sequence[Point], x_lower_is_better: bool = True, y_higher_is_better: bool = True
) -> list[Point]:
    """Points not dominated by another (no other is at least as good on both axes and better on one).

    Returned in order of increasing cost (decreasing x when a higher x is better).
    """
    sx = 1.0 if x_lower_is_better else -1.0
    sy = 1.0 if y_higher_is_better else -1.0
    ordered = sorted(points, key=lambda p: (sx * p.x, -sy * p.y))
    front: list[Point] = []
    for p in ordered:
        if not front or sy * p.y > sy * front[-1].y:
            front.append(p)
    return front


@dataclass(frozen=True)
class _Style:
    """Markers per method, colours per column (or per method when there is at most one column)."""

    methods: tuple[str, ...]
    cols: tuple[str, ...]

    @classmethod
    def of(cls, methods: Iterable[str], cols: Iterable[str]) -> _Style:
        return cls(tuple(dict.fromkeys(methods)), tuple(c for c in dict.fromkeys(cols) if c))

    def marker(self, method: str) -> str:
        return MARKERS[self.methods.index(method) % len(MARKERS)]

    def colour(self, method: str, col: str) -> str | tuple[float, ...]:
        if len(self.cols) <= 1:
            return f"C{self.methods.index(method) % 10}"
        from matplotlib import colormaps

        return colormaps["viridis"](self.cols.index(col) / max(1, len(self.cols) - 1) * 0.85)


def _col_order(cols: Sequence[str]) -> dict[str, tuple]:
    """Sort key of column labels: numerically where the value after '=' is a number."""

    def key(label: str) -> tuple:
        value = label.split("=", 1)[-1]
        try:
            return (0, float(value), label)
        except ValueError:
            return (1, 0.0, label)

    return {c: key(c) for c in cols}


def _natural(label: str) -> tuple:
    """Sort key: runs of digits compare as numbers (head_width=32 before head_width=128)."""
    return tuple(int(t) if t.isdigit() else t for t in re.split(r"(\d+)", label))


def _log_time_axis(ax) -> None:
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.xaxis.set_major_formatter(EngFormatter())
    ax.xaxis.set_minor_formatter(NullFormatter())


def save_figure(fig: Figure, path: Path | str, fmt: str, dpi: int, **kwargs: Any) -> Path:
    """Render ``fig`` as ``fmt`` into memory and write it to ``path`` with the atomic writer (a reader never
    sees a part; writers never share a temporary); ``kwargs`` go to ``savefig``. Returns the path."""
    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=dpi, **kwargs)
    atomic_write_bytes(path, buf.getvalue())
    return Path(path)


def _save(fig: Figure, out_dir: Path, stem: str) -> list[Path]:
    """Write ``<stem>.png`` and ``<stem>.svg`` (the SVG without a date, so that redraws compare equal); the
    bounding box is fitted to the drawing, so a legend wider than the figure is not clipped."""
    return [save_figure(fig, out_dir / f"{stem}.{fmt}", fmt, 120, bbox_inches="tight",
                        metadata={"Date": None} if fmt == "svg" else None)
            for fmt in ("png", "svg")]


def drawable_qualities(data: ChartData) -> list[str]:
    """The qualities of ``data`` with points (one row of panels each).

    Raises:
        ValueError: no point to draw.
    """
    qualities = [q for q in QUALITIES if data.points.get(q)]
    if not qualities:
        raise ValueError("nothing to chart: no ok run has psnr/ssim together with train_s")
    return qualities


def draw_chart(data: ChartData, out_dir: Path, stem: str = "chart") -> list[Path]:
    """Draw ``data`` (rows: qualities, columns: scenes); write ``<stem>.png`` and ``<stem>.svg``.

    Raises:
        ValueError: no point to draw.
    """
    qualities = drawable_qualities(data)
    all_points = [p for q in qualities for p in data.points[q]]
    panels = sorted({p.panel for p in all_points} | {f[0] for f in data.failed_x if f[2] is not None})
    style = _Style.of(sorted({p.row for p in all_points} | set(data.failed), key=_natural),
                      sorted({p.col for p in all_points}, key=lambda c: _col_order([c])[c]))  # fmt: skip

    fig = Figure(figsize=(max(7.0, 2.4 + 3.9 * len(panels)), 0.9 + 3.3 * len(qualities)), layout="constrained")
    axes = fig.subplots(len(qualities), len(panels), squeeze=False)
    for i, quality in enumerate(qualities):
        for j, panel in enumerate(panels):
            ax = axes[i][j]
            points = [p for p in data.points[quality] if p.panel == panel]
            _log_time_axis(ax)
            ax.grid(True, which="major", alpha=0.3)
            ax.set_ylabel(f"test {quality} ({'↑' if data.higher.get(quality, True) else '↓'})")
            if i == len(qualities) - 1:
                ax.set_xlabel(data.x_label, fontsize=8)
            if i == 0:
                ax.set_title(f"scene {panel}" if panel else ALL_RUNS, fontsize=10)
            by_method: dict[str, list[Point]] = defaultdict(list)
            for p in points:
                by_method[p.row].append(p)
            for method, pts in by_method.items():
                order = _col_order([p.col for p in pts])
                pts = sorted(pts, key=lambda p: order[p.col])
                if len(pts) > 1:
                    ax.plot([p.x for p in pts], [p.y for p in pts], color="0.7", lw=0.8, zorder=1)
                for p in pts:
                    # asymmetric x error so that a log axis never sees a non-positive end
                    xerr = [[min(p.x_err, 0.95 * p.x)], [p.x_err]]
                    ax.errorbar(p.x, p.y, xerr=xerr, yerr=p.y_err, color=style.colour(method, p.col),
                                marker=style.marker(method), markersize=6, markeredgecolor="black",
                                markeredgewidth=0.5, ecolor="0.35", elinewidth=0.8, capsize=2,
                                linestyle="none", zorder=3)  # fmt: skip
            fails = [x for (pn, _, x) in data.failed_x if pn == panel and x is not None and x > 0]
            if fails:
                ax.plot(fails, [0.03] * len(fails), linestyle="none", marker="x", color=FAILED_COLOUR,
                        markersize=8, mew=2, transform=ax.get_xaxis_transform(), zorder=4)  # fmt: skip
            if points:
                front = pareto_front(points, True, data.higher.get(quality, True))
                ax.step([p.x for p in front], [p.y for p in front], where="post", color="0.15",
                        linestyle="--", linewidth=1.0, zorder=2)  # fmt: skip
            else:
                ax.text(0.5, 0.5, "no ok run", ha="center", va="center", transform=ax.transAxes)

    def method_label(method: str) -> str:
        failed, total = data.failed.get(method, (0, 0))
        return f"{method} ({failed}/{total} runs failed)" if failed else method

    solo = len(style.cols) <= 1
    handles = [Line2D([], [], marker=style.marker(m), linestyle="none", markeredgecolor="black",
                      markeredgewidth=0.5, color=style.colour(m, "") if solo else "0.85", label=method_label(m))
               for m in style.methods]  # fmt: skip
    handles.append(Line2D([], [], color="0.15", ls="--", lw=1.0, label="Pareto front"))
    if data.failed_x:
        handles.append(Line2D([], [], color=FAILED_COLOUR, marker="x", mew=2, ls="none",
                              label="failed run (at its training time)"))  # fmt: skip
    legend = fig.legend(handles=handles, title="method", loc="outside right upper", fontsize=8, title_fontsize=8)
    if not solo:
        fig.add_artist(legend)
        col_handles = [Line2D([], [], marker="o", ls="none", color=style.colour(style.methods[0], c), label=c)
                       for c in style.cols]  # fmt: skip
        fig.legend(handles=col_handles, title="column", loc="outside right lower", fontsize=8, title_fontsize=8)
    title = data.title or "Speed against accuracy"
    fig.suptitle(f"{title}\nspeed against accuracy, mean ± std over seeds", fontsize=9)
    return _save(fig, out_dir, stem)


def make_chart(records: Iterable[RunRecord], spec: ReportSpec, out_dir: Path) -> list[Path]:
    """Speed against accuracy of sweep records: write ``chart.png`` and ``chart.svg`` in ``out_dir``.

    Raises:
        ValueError: no ``ok`` run has both a quality metric and ``train_s``.
    """
    return draw_chart(chart_data(records, spec), out_dir)


# -- learning curves ------------------------------------------------------------------------------


def read_curve(record: RunRecord) -> list[tuple[float, float]]:
    """(wall_s, psnr) of a record's ``curve`` entry, in order; entries that are not finite are dropped."""
    curve = record.data.get("curve")
    if not isinstance(curve, list):
        return []
    out = []
    for item in curve:
        if not isinstance(item, Mapping):
            continue
        t, y = item.get("wall_s"), item.get("psnr")
        if all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in (t, y)):
            out.append((float(t), float(y)))
    return sorted(out)


def make_curves(records: Iterable[RunRecord], spec: ReportSpec, out_dir: Path) -> list[Path]:
    """Held-out PSNR against wall time of every record with a ``curve``; ``curves.png`` / ``.svg``.

    One panel per scene, one line per run (colour and marker as in :func:`make_chart`); a failed
    run's line is dotted and ends with a red ✕. Returns [] (and writes nothing) without curves.
    """
    records, _ = dedupe(records)
    runs = []
    for record in records:
        labels = _labels(record, spec) if record.status in ("ok", "failed") else None
        curve = read_curve(record) if labels else []
        if labels and curve:
            runs.append((labels, record.status, [(t, y) for t, y in curve if t > 0]))
    runs = [r for r in runs if r[2]]
    if not runs:
        return []
    panels = sorted({labels[0] for labels, _, _ in runs})
    style = _Style.of(sorted({labels[1] for labels, _, _ in runs}, key=_natural),
                      sorted({labels[2] for labels, _, _ in runs}, key=lambda c: _col_order([c])[c]))  # fmt: skip
    fig = Figure(figsize=(max(7.0, 2.4 + 3.9 * len(panels)), 4.0), layout="constrained")
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels, strict=True):
        _log_time_axis(ax)
        ax.grid(True, which="major", alpha=0.3)
        ax.set_title(f"scene {panel}" if panel else ALL_RUNS, fontsize=10)
        ax.set_xlabel("wall time [s] (log)", fontsize=8)
        ax.set_ylabel("held-out PSNR (↑)")
        for (pn, method, col), status, curve in runs:
            if pn != panel:
                continue
            colour = style.colour(method, col)
            ax.plot([t for t, _ in curve], [y for _, y in curve], color=colour, marker=style.marker(method),
                    markersize=4, markevery=max(1, len(curve) // 6), lw=1.0,
                    ls=":" if status == "failed" else "-")  # fmt: skip
            if status == "failed":
                ax.plot(*curve[-1], marker="x", color=FAILED_COLOUR, markersize=8, mew=2)
    handles = [Line2D([], [], marker=style.marker(m), color=style.colour(m, "") if len(style.cols) <= 1 else "0.4",
                      label=m) for m in style.methods]  # fmt: skip
    handles += [Line2D([], [], color=style.colour(style.methods[0], c), lw=2, label=c) for c in style.cols
                if len(style.cols) > 1]  # fmt: skip
    if any(status == "failed" for _, status, _ in runs):
        handles.append(Line2D([], [], color="0.4", ls=":", marker="x", mec=FAILED_COLOUR, label="failed run"))
    fig.legend(handles=handles, loc="outside right upper", fontsize=8)
    fig.suptitle(f"{spec.title or 'Learning curves'}\nheld-out PSNR against wall time, one line per run", fontsize=9)
    return _save(fig, out_dir, "curves")


# -- from a table.md written by src.tables --------------------------------------------------------


def chart_from_table_md(text: str) -> ChartData:
    """Chart data from a Markdown ``table.md`` of :mod:`src.tables` with a ``train_s`` table.

    Raises:
        ValueError: the text has no ``train_s`` table or no quality table.
    """
    from src.reporting.table_md import parse_tables

    tables = {t.metric: t for t in parse_tables(text)}
    if "train_s" not in tables or not any(q in tables for q in QUALITIES):
        raise ValueError(f"nothing to chart: the tables are {sorted(tables)}; need train_s and psnr or ssim")
    times = tables["train_s"]
    data = ChartData(points={}, higher={}, title=times.title,
                     x_label="training time train_s [s] (log; as tabulated)")  # fmt: skip
    for quality in QUALITIES:
        if quality not in tables:
            continue
        table = tables[quality]
        data.higher[quality] = table.higher_is_better
        data.points[quality] = []
        for row in table.rows:
            for col, cell in row.cells.items():
                t = times.cell(row.keys, col)
                if cell is None or t is None or t.mean <= 0:
                    continue
                panel, method, column = table.labels(row.keys, col)
                data.points[quality].append(Point(method, column, t.mean, t.std, cell.mean, cell.std, cell.n, panel))
    for row in times.rows:
        _, method, _ = times.labels(row.keys, next(iter(row.cells), ""))
        failed, total = data.failed.get(method, (0, 0))
        data.failed[method] = (failed + row.failed[0], total + row.failed[1])
    return data


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m src.reporting.chart --from-table TABLE.md [--out DIR]``: the chart of a table.md.

    Exit codes: 0 written; 2 an unreadable table, one without a chart, or an output folder that cannot
    be written (one line on stderr).
    """
    parser = OneLineParser(prog="python -m src.reporting.chart", description=main.__doc__)
    parser.add_argument("--from-table", type=Path, required=True, metavar="TABLE.md")
    parser.add_argument("--out", type=Path, help="directory for chart.png / chart.svg (default: the table's)")
    args = parser.parse_args(argv)
    try:
        text = args.from_table.read_text(encoding="utf-8")
        data = chart_from_table_md(text)
    except OSError as exc:
        return cli_error(f"--from-table: {os_error_line(exc)}")
    except (UnicodeDecodeError, ValueError) as exc:
        return cli_error(f"--from-table {args.from_table}: {exc}")
    out = args.out or args.from_table.parent
    try:
        with output_lock(out, "choose another --out"):
            paths = draw_chart(data, out)
    except OutputBusy as exc:
        return cli_error(str(exc))
    except OSError as exc:
        return cli_error(f"--out: {os_error_line(exc)}")
    for path in paths:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
