"""Group run records into tables and aggregate over seeds: mean ± sample std, ranks, failure rates.

Pure: records and a :class:`ReportSpec` in, a :class:`Report` (plain data) out. Rendering to
Markdown / LaTeX / CSV lives in :mod:`src.reporting.render`.
"""

from __future__ import annotations

import json
import statistics
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from src.reporting import paper_numbers
from src.reporting.collect import Problem, RunRecord

DEFAULT_ROWS = ("method",)
DEFAULT_COLS = ("keys.n_views",)
DEFAULT_METRICS = ("psnr", "ssim")
# Metrics where a smaller value is better unless the report block says otherwise.
LOWER_IS_BETTER = frozenset(
    {"lpips", "st_lpips", "iter_ms", "train_s", "n_splats", "n_params", "peak_mem_mb", "delta_psnr"}
)
# Keys (last dotted component) that locate a published number: the view count and the scene.
_VIEWS_KEY, _SCENE_KEY = "n_views", "scene"

Key = tuple[Any, ...]


@dataclass(frozen=True)
class ReportSpec:
    """How to tabulate a sweep (the ``report:`` block; CLI flags override it).

    Attributes:
        title: table caption.
        rows: dotted paths into metrics.json whose values identify a table row (``method``).
        cols: dotted paths identifying a column (``keys.n_views``); empty → one column per metric.
        metrics: names under ``metrics``; one table per metric (when ``cols`` is not empty).
        higher_is_better: per-metric direction overriding the defaults (see :data:`LOWER_IS_BETTER`).
        quoted: append the paper's rows: a table reference (``"C.1"``), ``"auto"`` (pick by
            ``choices.dataset``), or None (do not quote).
        seed_key: dotted path of the seed, shown for failed runs.
        decimals: per-metric number of decimals overriding the magnitude-based default.
    """

    title: str = ""
    rows: tuple[str, ...] = DEFAULT_ROWS
    cols: tuple[str, ...] = DEFAULT_COLS
    metrics: tuple[str, ...] = DEFAULT_METRICS
    higher_is_better: Mapping[str, bool] = field(default_factory=dict)
    quoted: str | None = None
    seed_key: str = "keys.seed"
    decimals: Mapping[str, int] = field(default_factory=dict)

    @classmethod
    def from_mapping(cls, block: Mapping[str, Any] | None) -> ReportSpec:
        """Build from a ``report:`` block; missing fields take the defaults.

        Raises:
            ValueError: a field has the wrong type (the message names the field).
        """
        if block is None:
            return cls()
        if not isinstance(block, Mapping):
            raise ValueError(f"report block is {type(block).__name__}, expected a mapping")
        kwargs: dict[str, Any] = {}  # keys not read here (e.g. future format options) are ignored
        for name in ("rows", "cols", "metrics"):
            if name in block:
                kwargs[name] = _str_tuple(block[name], f"report.{name}")
        for name in ("higher_is_better", "decimals"):
            value = block.get(name) or {}
            if not isinstance(value, Mapping):
                raise ValueError(f"report.{name} must be a mapping, got {type(value).__name__}")
            kwargs[name] = dict(value)
        for name in ("title", "seed_key"):
            if block.get(name) is not None:
                kwargs[name] = str(block[name])
        quoted = block.get("quoted")
        if quoted is True:
            kwargs["quoted"] = "auto"
        elif quoted not in (None, False):
            kwargs["quoted"] = str(quoted)
        return cls(**kwargs)

    def with_overrides(self, **overrides: Any) -> ReportSpec:
        """A copy with the given fields replaced; ``None`` values leave the field unchanged."""
        return replace(self, **{k: v for k, v in overrides.items() if v is not None})

    def is_higher_better(self, metric: str) -> bool:
        """Direction of ``metric``: the report block's ``higher_is_better``, else the default."""
        if metric in self.higher_is_better:
            return bool(self.higher_is_better[metric])
        return metric not in LOWER_IS_BETTER


def _str_tuple(value: Any, name: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if isinstance(value, str):
        return tuple(v.strip() for v in value.split(",") if v.strip())
    if isinstance(value, Sequence) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise ValueError(f"{name} must be a list of strings, got {value!r}")


@dataclass(frozen=True)
class Cell:
    """Aggregate of one (row, column) group for one metric.

    Attributes:
        values: the metric of every ``ok`` run in the group (finite values only).
        n_failed: runs with ``status == "failed"`` in the group.
        n_total: all runs in the group (ok, failed, running).
    """

    values: tuple[float, ...] = ()
    n_failed: int = 0
    n_total: int = 0

    @property
    def n(self) -> int:
        return len(self.values)

    @property
    def mean(self) -> float | None:
        return statistics.fmean(self.values) if self.values else None

    @property
    def std(self) -> float | None:
        """Sample standard deviation (n − 1); None for fewer than two values."""
        return statistics.stdev(self.values) if len(self.values) >= 2 else None


@dataclass(frozen=True)
class Column:
    """A table column: the values of the ``cols`` keys and the metric shown in it."""

    key: Key
    metric: str
    label: str


@dataclass(frozen=True)
class QuotedRow:
    """A published row from the paper, aligned to a table's columns (values as printed)."""

    row: Key
    system: str
    refs: tuple[str, ...]
    values: tuple[float | None, ...]
    decimals: tuple[int, ...]
    note: str


@dataclass
class Table:
    """One rendered table: rows × columns of :class:`Cell`, with ranks and per-row statistics.

    Attributes:
        metric: the metric of every column, or None when the columns are the metrics.
        ranks: (row, column index) → 1, 2 or 3 for the best three cells of each column, among rows of
            the same scene / n_views when those are row keys.
        failures: row → (failed runs, all runs) over every column and seed of the row.
        stability: row → mean over the row's cells of the seed-to-seed sample std (None if no cell
            has two or more runs, or when the columns hold different metrics).
    """

    title: str
    metric: str | None
    row_keys: tuple[str, ...]
    col_keys: tuple[str, ...]
    rows: list[Key]
    columns: list[Column]
    cells: dict[tuple[Key, int], Cell]
    ranks: dict[tuple[Key, int], int]
    failures: dict[Key, tuple[int, int]]
    stability: dict[Key, float | None]
    higher_is_better: tuple[bool, ...]
    quoted: list[QuotedRow] = field(default_factory=list)


@dataclass(frozen=True)
class FailedRun:
    """A run that did not finish ``ok``, for the list under the tables."""

    row: Key
    col: Key
    seed: Any
    status: str
    message: str
    run_dir: str


@dataclass
class Report:
    """Everything the renderers need: tables, failed runs, skipped files and notes."""

    spec: ReportSpec
    tables: list[Table]
    failed: list[FailedRun]
    problems: list[Problem]
    notes: list[str]
    n_records: int  # runs tabulated or listed (after de-duplication)


def sort_key(value: Any) -> tuple[int, Any]:
    """Natural order for mixed cell keys: numbers numerically, then strings, then the rest."""
    if isinstance(value, bool) or value is None:
        return (2, str(value))
    if isinstance(value, int | float):
        return (0, value)
    if isinstance(value, str):
        return (1, value)
    return (2, str(value))


def _hashable(value: Any) -> Any:
    return json.dumps(value, sort_keys=True) if isinstance(value, dict | list) else value


def group_key(record: RunRecord, paths: Sequence[str]) -> Key:
    """The (hashable) values of ``record`` at the dotted ``paths``; KeyError naming a missing path."""
    return tuple(_hashable(record.get(p)) for p in paths)


def run_identity(record: RunRecord) -> str:
    """What makes two records the same run: experiment, method, choices, keys and overrides."""
    data = record.data
    parts = [data.get(k) for k in ("experiment", "method", "choices", "keys")]
    parts.append(sorted(map(str, data.get("overrides") or [])))
    return json.dumps(parts, sort_keys=True, default=str)


def _preference(record: RunRecord) -> tuple[bool, float, str]:
    """Which of two duplicate records to keep: ``ok`` first, then the newest file."""
    return (record.status == "ok", record.mtime, record.path)


def dedupe(records: Iterable[RunRecord]) -> tuple[list[RunRecord], list[str]]:
    """Keep one record per :func:`run_identity`: an ``ok`` one if any, else the newest.

    This lets several sweep directories (a re-run after a failure) be tabulated together without
    counting a run twice. Returns the kept records and one note per superseded file.
    """
    best: dict[str, RunRecord] = {}
    notes = []
    for record in records:
        ident = run_identity(record)
        other = best.get(ident)
        if other is None:
            best[ident] = record
            continue
        keep, drop = (record, other) if _preference(record) > _preference(other) else (other, record)
        best[ident] = keep
        notes.append(f"duplicate run {drop.path} superseded by {keep.path} (same run identity)")
    return list(best.values()), notes


def _rank(cells: Sequence[tuple[Key, float]], higher_is_better: bool) -> dict[Key, int]:
    """Competition ranks (1, 1, 3, ...) of ``(row, mean)`` pairs; ties share a rank."""
    ordered = sorted(cells, key=lambda rc: -rc[1] if higher_is_better else rc[1])
    ranks: dict[Key, int] = {}
    for i, (row, value) in enumerate(ordered):
        ranks[row] = ranks[ordered[i - 1][0]] if i and value == ordered[i - 1][1] else i + 1
    return ranks


def _short(path: str) -> str:
    return path.rsplit(".", 1)[-1]


def column_label(col_keys: Sequence[str], key: Key) -> str:
    """Header text of a column: ``n_views=8`` (joined with ", " for several keys)."""
    return ", ".join(f"{_short(k)}={v}" for k, v in zip(col_keys, key, strict=True))


def build_report(
    records: Iterable[RunRecord],
    spec: ReportSpec,
    problems: Iterable[Problem] = (),
) -> Report:
    """Aggregate records into the tables described by ``spec``.

    Records are deduplicated (:func:`dedupe`) and grouped by the values at ``spec.rows`` and
    ``spec.cols``. Each cell is the mean ± sample std of the metric over the ``ok`` runs of its group
    (its seeds); a group without an ``ok`` run has no value. An ``ok`` record lacking a row/column
    key is skipped and reported in ``problems``; failed runs lacking one are only listed.
    """
    records, notes = dedupe(records)
    problems = list(problems)
    grouped: dict[tuple[Key, Key], list[RunRecord]] = defaultdict(list)
    failed: list[FailedRun] = []
    n_unplaced = 0  # failed/running records whose row/column keys are missing: listed, not tabulated
    for record in sorted(records, key=lambda r: r.path):
        try:
            row, col = group_key(record, spec.rows), group_key(record, spec.cols)
        except KeyError as exc:
            row = col = None
            if record.status == "ok":
                problems.append(Problem(record.path, f"lacks {exc.args[0]!r} (a report row/column key)"))
                continue
        if record.status != "ok":
            seed = _lookup(record, spec.seed_key)
            failed.append(FailedRun(row or (), col or (), seed, record.status, record.message(), record.run_dir))
        if row is not None and col is not None:
            grouped[(row, col)].append(record)
        else:
            n_unplaced += 1

    rows = sorted({r for r, _ in grouped}, key=lambda k: tuple(map(sort_key, k)))
    col_values = sorted({c for _, c in grouped}, key=lambda k: tuple(map(sort_key, k)))
    failures = {row: _failure_count(grouped, row) for row in rows}
    if spec.cols:
        layouts = [(m, [Column(c, m, column_label(spec.cols, c)) for c in col_values]) for m in spec.metrics]
    else:
        layouts = [(None, [Column((), m, m) for m in spec.metrics])]

    tables = []
    for metric, columns in layouts:
        table = _make_table(spec, metric, columns, rows, grouped, failures, notes)
        if spec.quoted:
            table.quoted, quote_notes = quoted_rows(table, spec.quoted, grouped)
            notes.extend(quote_notes)
        tables.append(table)
    n_records = sum(len(v) for v in grouped.values()) + n_unplaced
    failed.sort(key=lambda f: (tuple(map(sort_key, f.row + f.col)), sort_key(f.seed), f.run_dir))
    return Report(spec, tables, failed, problems, notes, n_records)


def _lookup(record: RunRecord, dotted: str) -> Any:
    try:
        return record.get(dotted)
    except KeyError:
        return None


def _failure_count(grouped: Mapping[tuple[Key, Key], list[RunRecord]], row: Key) -> tuple[int, int]:
    runs = [r for (rk, _), rs in grouped.items() if rk == row for r in rs]
    return sum(r.status == "failed" for r in runs), len(runs)


def _make_table(
    spec: ReportSpec,
    metric: str | None,
    columns: list[Column],
    rows: list[Key],
    grouped: Mapping[tuple[Key, Key], list[RunRecord]],
    failures: dict[Key, tuple[int, int]],
    notes: list[str],
) -> Table:
    cells: dict[tuple[Key, int], Cell] = {}
    missing: dict[str, int] = defaultdict(int)
    for row in rows:
        for j, column in enumerate(columns):
            runs = grouped.get((row, column.key), [])
            ok = [r for r in runs if r.status == "ok"]
            values = [v for v in (r.metric(column.metric) for r in ok) if v is not None]
            missing[column.metric] += len(ok) - len(values)
            n_failed = sum(r.status == "failed" for r in runs)
            cells[(row, j)] = Cell(tuple(values), n_failed, len(runs))
    for name, count in missing.items():
        if count:
            notes.append(f"{count} ok run(s) have no finite value for metric '{name}'")

    directions = tuple(spec.is_higher_better(c.metric) for c in columns)
    # Rows that differ in a context key (scene, n_views) are different problems: rank methods only
    # against rows of the same context, as the paper ranks per scene / view-count column.
    context = list(_context_positions(spec.rows).values())
    ranks: dict[tuple[Key, int], int] = {}
    for j, higher in enumerate(directions):
        by_context: dict[Key, list[tuple[Key, float]]] = {}
        for row in rows:
            if cells[(row, j)].n:
                by_context.setdefault(tuple(row[i] for i in context), []).append((row, cells[(row, j)].mean))
        for scored in by_context.values():
            for row, rank in _rank(scored, higher).items():
                if rank <= 3:
                    ranks[(row, j)] = rank

    stability: dict[Key, float | None] = {}
    for row in rows:
        stds = [cells[(row, j)].std for j in range(len(columns))]
        stds = [s for s in stds if s is not None]
        stability[row] = statistics.fmean(stds) if stds and metric is not None else None

    title = spec.title or "Results"
    return Table(
        title=title,
        metric=metric,
        row_keys=spec.rows,
        col_keys=spec.cols,
        rows=rows,
        columns=columns,
        cells=cells,
        ranks=ranks,
        failures=failures,
        stability=stability,
        higher_is_better=directions,
    )


# --------------------------------------------------------------------------- quoted paper rows


def _context_positions(keys: Sequence[str]) -> dict[str, int]:
    return {_short(k): i for i, k in enumerate(keys) if _short(k) in (_VIEWS_KEY, _SCENE_KEY)}


def _fixed_value(records: Iterable[RunRecord], name: str) -> tuple[bool, Any]:
    """(True, v) if every record has the same ``keys.<name>`` value v; (False, values) otherwise."""
    values = {_hashable(_lookup(r, f"keys.{name}")) for r in records}
    return (True, values.pop()) if len(values) == 1 else (False, values)


def _as_views(value: Any) -> int | None:
    try:
        return int(value)
    except (TypeError, ValueError):
        return None


def quoted_rows(
    table: Table, quoted: str, grouped: Mapping[tuple[Key, Key], list[RunRecord]]
) -> tuple[list[QuotedRow], list[str]]:
    """The paper's published rows for the systems this table did not run, aligned to its columns.

    ``quoted`` is a supplementary table reference (``"C.1"``; its sibling block is used for other
    metrics, e.g. C.2 for SSIM) or ``"auto"`` (chosen by the runs' ``choices.dataset``). The view
    count and scene of each cell come from a ``*.n_views`` / ``*.scene`` row or column key, else
    from the value all runs share; runs spanning several scenes are compared with the paper's
    "mean" column. Values are as printed (SSIM/LPIPS ×100). Returns the rows and explanatory notes.
    """
    records = [r for rs in grouped.values() for r in rs if r.status == "ok"]
    notes: list[str] = []
    if quoted == "auto":
        same, dataset = _fixed_dataset(records)
        if not same:
            return [], [f"quoted rows skipped: runs use several datasets {sorted(map(str, dataset))}"]
        papers = [paper_numbers.table_for_dataset(str(dataset), c.metric) for c in table.columns]
        source = f"dataset '{dataset}'"
    else:
        papers = [paper_numbers.find_table(quoted, c.metric) for c in table.columns]
        source = f"Tab. {quoted}"
    for column, paper in zip(table.columns, papers, strict=True):
        if paper is None:
            notes.append(f"no published '{column.metric}' numbers for {source}")
    if all(p is None for p in papers):
        return [], notes

    row_ctx = _context_positions(table.row_keys)
    col_ctx = _context_positions(table.col_keys)
    system_pos = next((i for i, k in enumerate(table.row_keys) if _short(k) not in row_ctx), None)
    if system_pos is None:
        return [], [*notes, "quoted rows skipped: no row key names a method"]
    fixed = {name: _fixed_value(records, name) for name in (_VIEWS_KEY, _SCENE_KEY)}
    scene_in_labels = _SCENE_KEY in row_ctx or _SCENE_KEY in col_ctx
    if not fixed[_SCENE_KEY][0] and not scene_in_labels:
        notes.append("runs span several scenes: quoted values are the paper's 'mean' column")

    projections = sorted({tuple(row[i] for i in row_ctx.values()) for row in table.rows}, key=str)
    run_labels = {row[system_pos] for row in table.rows}
    systems = list(dict.fromkeys(s for p in papers if p is not None for s in p.rows))
    unmatched = [s for s in systems if not any(paper_numbers.system_matches(s, str(label)) for label in run_labels)]
    out = []
    for system in unmatched:
        for projection in projections or [()]:
            from_row = dict(zip(row_ctx, projection, strict=True))
            values, decimals, refs, used = [], [], [], set()
            for column, paper in zip(table.columns, papers, strict=True):
                ctx = {**from_row, **{n: column.key[i] for n, i in col_ctx.items()}}
                value, paper_column = _paper_value(paper, system, ctx, fixed) if paper else (None, None)
                values.append(value)
                decimals.append(paper.decimals if paper else 2)
                if paper and paper_column is not None:  # printed, possibly as "-" (value None)
                    refs += [paper.ref] if paper.ref not in refs else []
                    used.add(paper_column)
            if not refs:
                continue
            row = [""] * len(table.row_keys)
            row[system_pos] = system
            for name, value in from_row.items():
                row[row_ctx[name]] = value
            note = _quote_note(refs, papers, used.pop() if len(used) == 1 and not scene_in_labels else None)
            out.append(QuotedRow(tuple(row), system, tuple(refs), tuple(values), tuple(decimals), note))
    if unmatched and not out:
        views, scene = (fixed[n][1] if fixed[n][0] else "several/unknown" for n in (_VIEWS_KEY, _SCENE_KEY))
        notes.append(f"no published values match these runs (n_views={views}, scene={scene})")
    return out, notes


def _fixed_dataset(records: Sequence[RunRecord]) -> tuple[bool, Any]:
    values = {str(_lookup(r, "choices.dataset")) for r in records}
    return (True, values.pop()) if len(values) == 1 else (False, values)


def _paper_value(
    paper: paper_numbers.PaperTable,
    system: str,
    ctx: Mapping[str, Any],
    fixed: Mapping[str, tuple[bool, Any]],
) -> tuple[float | None, str | None]:
    """The printed value for a cell context and its paper column; (None, column) for a printed "-",
    (None, None) if the table has no such entry."""
    views = ctx.get(_VIEWS_KEY, fixed[_VIEWS_KEY][1] if fixed[_VIEWS_KEY][0] else None)
    if _SCENE_KEY in ctx:
        scene = ctx[_SCENE_KEY]
    else:
        scene = fixed[_SCENE_KEY][1] if fixed[_SCENE_KEY][0] else None
    column = paper_numbers.scene_column(paper, scene)
    if column is None:
        return None, None
    try:
        return paper.lookup(system, _as_views(views), column), column
    except (KeyError, ValueError):  # system, view count or column not in this table
        return None, None


def _quote_note(refs: Sequence[str], papers: Sequence[paper_numbers.PaperTable | None], column: str | None) -> str:
    """``(quoted, supplementary Tab. C.1, column Toy; SSIM ×100)``: source, paper column, units."""
    text = "quoted, supplementary Tab. " + "/".join(refs)
    if column is not None:
        text += f", column {column}"
    scaled = sorted({f"{p.metric.upper()} ×{p.scale:g}" for p in papers if p and p.scale != 1.0})
    return f"({text}; {', '.join(scaled)})" if scaled else f"({text})"
