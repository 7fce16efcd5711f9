"""Speed × accuracy charts: test quality against training time, model size and baked render FPS.

One point per (row, column) group of the report (e.g. method × n_views): the mean over its ``ok``
runs (seeds) with sample-std error bars on both axes. One colour/marker per row (method). The
Pareto front of each panel (best quality for less cost) is drawn as a dashed staircase with ringed
points. Uses matplotlib's object API with the Agg canvas, so no global backend is changed.
"""

from __future__ import annotations

import os
import statistics
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.ticker import EngFormatter, LogLocator, NullFormatter

from src.reporting.aggregate import Key, ReportSpec, column_label, dedupe, group_key
from src.reporting.collect import RunRecord

QUALITIES = ("psnr", "ssim")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "h", "<", ">")


def _size(record: RunRecord) -> float | None:
    parts = [record.metric("n_params"), record.metric("n_splats")]
    return None if all(p is None for p in parts) else sum(p or 0.0 for p in parts)


def _train_time(record: RunRecord) -> float | None:
    """Training time including a 3DGS first stage (two-stage protocol, ``stage1_train_s``) and a
    capacity search (``capacity_search_s``)."""
    t = record.metric("train_s")
    return None if t is None else t + (record.metric("stage1_train_s") or 0.0) + (
        record.metric("capacity_search_s") or 0.0)


@dataclass(frozen=True)
class Cost:
    """An x axis: how to read it from a record, its label, scale and direction."""

    name: str
    label: str
    read: Callable[[RunRecord], float | None]
    log: bool
    lower_is_better: bool


COSTS = (
    Cost("train_s", "training time train_s (+ first stage, capacity search) [s]", _train_time, False, True),
    Cost("size", "model size n_params + n_splats", _size, True, True),
    Cost("fps_baked", "render FPS of the baked model", lambda r: r.metric("fps_baked"), False, False),
)


@dataclass(frozen=True)
class Point:
    """Mean ± sample std of one group on one panel (std is 0 for a single run)."""

    row: str
    col: str
    x: float
    x_err: float
    y: float
    y_err: float
    n: int


def _std(values: Sequence[float]) -> float:
    return statistics.stdev(values) if len(values) >= 2 else 0.0


def chart_points(records: Iterable[RunRecord], spec: ReportSpec, quality: str, cost: Cost) -> list[Point]:
    """Points of one panel: ``ok`` runs grouped by report rows × cols; runs lacking x or y are skipped."""
    groups: dict[tuple[Key, Key], list[tuple[float, float]]] = defaultdict(list)
    for record in records:
        if record.status != "ok":
            continue
        try:
            key = (group_key(record, spec.rows), group_key(record, spec.cols))
        except KeyError:
            continue  # reported by the table builder
        x, y = cost.read(record), record.metric(quality)
        if x is not None and y is not None:
            groups[key].append((x, y))
    points = []
    for (row, col), pairs in sorted(groups.items(), key=lambda kv: str(kv[0])):
        xs, ys = [p[0] for p in pairs], [p[1] for p in pairs]
        label = " / ".join(map(str, row))
        points.append(
            Point(label, column_label(spec.cols, col), statistics.fmean(xs), _std(xs),
                  statistics.fmean(ys), _std(ys), len(pairs))
        )  # fmt: skip
    return points


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


def make_chart(records: Iterable[RunRecord], spec: ReportSpec, out_dir: Path) -> list[Path]:
    """Draw PSNR (top row) and SSIM (bottom row) against each cost; write ``chart.png`` and ``chart.svg``.

    Panels without data (e.g. no ``fps_baked`` in any run) are left out. Returns the written paths.

    Raises:
        ValueError: no ``ok`` run has both a quality metric and a cost.
    """
    records, _ = dedupe(records)
    panels = {(q, c.name): chart_points(records, spec, q, c) for q in QUALITIES for c in COSTS}
    qualities = [q for q in QUALITIES if any(panels[(q, c.name)] for c in COSTS)]
    costs = [c for c in COSTS if any(panels[(q, c.name)] for q in QUALITIES)]
    if not qualities or not costs:
        raise ValueError(
            "nothing to chart: no ok run has psnr/ssim together with train_s, n_params/n_splats or fps_baked"
        )
    labels = sorted({p.row for pts in panels.values() for p in pts})
    style = {label: (f"C{i % 10}", MARKERS[i % len(MARKERS)]) for i, label in enumerate(labels)}
    several_cols = len({p.col for pts in panels.values() for p in pts}) > 1

    fig = Figure(figsize=(4.6 * len(costs), 3.8 * len(qualities)), layout="constrained")
    axes = fig.subplots(len(qualities), len(costs), squeeze=False)
    for i, quality in enumerate(qualities):
        higher = spec.is_higher_better(quality)
        for j, cost in enumerate(costs):
            ax, points = axes[i][j], panels[(quality, cost.name)]
            ax.set_xlabel(cost.label)
            ax.set_ylabel(f"test {quality} ({'↑' if higher else '↓'})")
            ax.grid(True, alpha=0.3)
            if cost.log:
                ax.set_xscale("log")
                ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
                ax.xaxis.set_major_formatter(EngFormatter())
                ax.xaxis.set_minor_formatter(NullFormatter())
            if not points:
                ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
                continue
            for p in points:
                colour, marker = style[p.row]
                ax.errorbar(p.x, p.y, xerr=p.x_err, yerr=p.y_err, color=colour, marker=marker,
                            markersize=6, capsize=3, linestyle="none")  # fmt: skip
                if several_cols:
                    ax.annotate(p.col, (p.x, p.y), textcoords="offset points", xytext=(4, 4), fontsize=7)
            front = pareto_front(points, cost.lower_is_better, higher)
            ax.step([p.x for p in front], [p.y for p in front], where="post", color="0.3",
                    linestyle="--", linewidth=1)  # fmt: skip
            ax.scatter([p.x for p in front], [p.y for p in front], s=150, facecolors="none",
                       edgecolors="0.3", linewidths=1)  # fmt: skip
    handles = [
        axes[0][0].errorbar([], [], color=c, marker=m, linestyle="none", label=label) for label, (c, m) in style.items()
    ]
    front_handle = axes[0][0].plot([], [], color="0.3", ls="--", marker="o", mfc="none", label="Pareto front")
    handles.append(front_handle[0])
    fig.legend(handles=handles, loc="outside right upper", fontsize=8)
    fig.suptitle((spec.title or "Speed × accuracy") + " — mean ± std over seeds")

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for fmt in ("png", "svg"):
        path, tmp = out_dir / f"chart.{fmt}", out_dir / f".chart.{fmt}.tmp"
        fig.savefig(tmp, format=fmt, dpi=120)
        os.replace(tmp, path)  # readers never see a half-written file
        paths.append(path)
    return paths
