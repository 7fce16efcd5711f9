"""Tables and charts from sweep results (``python -m src.tables``).

Conventions:

* **The run record is the only input.** Every run writes one ``metrics.json`` in its run directory;
  a sweep directory holds ``multirun.yaml`` and ``<job>/…/metrics.json`` at any depth. Records are
  found with ``**/metrics.json`` and identified by their content (``method``, ``choices``, ``keys``,
  ``overrides``); directory names are never parsed.
* **metrics.json keys used here** (public contract): ``status`` ∈ {ok, failed, running}, ``error``,
  ``reason`` (divergence guard), ``experiment``, ``method``, ``choices``, ``overrides``, ``keys``
  (``scene``, ``n_views``, ``seed``, …), ``metrics`` (``psnr``, ``ssim`` in [0, 1], ``n_splats``,
  ``n_params``, ``train_s``, ``iter_ms``, ``peak_mem_mb``, optional ``fps_baked``, ``lpips``, …),
  ``report``. ``status`` is required; ``method``, ``keys`` and ``metrics`` too when it is ``ok``.
  A file that is not valid JSON or breaks these rules is reported (path + reason) and skipped.
* **The report block** (top level of ``multirun.yaml``, else the ``report`` copied into a record)
  says how to tabulate: ``rows``/``cols`` are dotted paths into metrics.json, ``metrics`` the names
  under ``metrics`` (one table each; no ``cols`` → one column per metric), ``higher_is_better``,
  ``quoted`` (a supplementary table such as ``"C.1"``), ``seed_key``. Defaults: rows ``[method]``,
  cols ``[keys.n_views]``, metrics ``[psnr, ssim]``. Command-line flags override the block.
* **Aggregation:** runs sharing a (row, column) key are seeds of one cell: mean ± sample std (n − 1)
  over the ``ok`` runs, n shown. A cell without an ``ok`` run prints "–". Duplicate runs (same
  experiment/method/choices/keys/overrides, e.g. a re-run in a second sweep directory) count once:
  an ``ok`` one wins, else the newest.
* **Published numbers** (:mod:`src.reporting.paper_numbers`) are appended verbatim, labelled
  "(quoted, supplementary Tab. C.x)", only for systems that were not run, and never ranked. The
  paper prints SSIM/LPIPS ×100; the label says so.

Modules: :mod:`.collect` (find/read/validate files), :mod:`.aggregate` (group, mean ± std, ranks,
quoted rows), :mod:`.render` (md/tex/csv text), :mod:`.chart` (speed × accuracy figures),
:mod:`.paper_numbers` (Tables C.1–C.6).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from src.reporting.aggregate import Report, ReportSpec, build_report
from src.reporting.collect import (
    Collection,
    Problem,
    RecordError,
    RunRecord,
    collect,
    record_from_mapping,
    report_from_records,
)
from src.reporting.render import Format, render

Source = Iterable[str | Path] | Iterable[RunRecord | Mapping[str, Any]]


def load(source: Source) -> Collection:
    """Records from sweep directories (paths) or from in-memory records / metrics.json dicts.

    Dicts are validated like files; invalid ones become :class:`Problem` entries.
    """
    items = list(source)
    if all(isinstance(x, str | Path) for x in items):
        return collect(items)  # type: ignore[arg-type]
    out = Collection()
    for i, item in enumerate(items):
        if isinstance(item, RunRecord):
            out.records.append(item)
        elif isinstance(item, Mapping):
            try:
                out.records.append(record_from_mapping(item, path=f"<record {i}>"))
            except RecordError as exc:
                out.problems.append(Problem(f"<record {i}>", str(exc)))
        else:
            raise TypeError(f"source item {i} is {type(item).__name__}; expected a path, RunRecord or dict")
    out.n_files = len(items)
    out.report = report_from_records(out.records)
    return out


def resolve_spec(spec: ReportSpec | Mapping[str, Any] | None, collection: Collection) -> ReportSpec:
    """The spec to use: the given one, else the sweep's report block, else the defaults."""
    if isinstance(spec, ReportSpec):
        return spec
    return ReportSpec.from_mapping(spec if spec is not None else collection.report)


def make_report(source: Source, spec: ReportSpec | Mapping[str, Any] | None = None) -> Report:
    """Read the runs of ``source`` and aggregate them into a :class:`Report` (see :func:`make_tables`)."""
    collection = load(source)
    return build_report(collection.records, resolve_spec(spec, collection), collection.problems)


def make_tables(
    source: Source,
    spec: ReportSpec | Mapping[str, Any] | None = None,
    fmt: Format = "md",
    quoted: str | None = None,
) -> str:
    """Tables of the runs in ``source`` as ``md``, ``tex`` or ``csv`` text.

    Args:
        source: sweep directories (searched for ``**/metrics.json``), or RunRecords / metrics dicts.
        spec: a :class:`ReportSpec` or ``report:`` mapping; None → the sweep's own block or defaults.
        fmt: output format.
        quoted: append the paper's published rows (``"C.1"``, ``"auto"``); overrides ``spec.quoted``.

    Only reads files; the returned text lists failed runs, skipped files and notes under the tables.
    """
    collection = load(source)
    resolved = resolve_spec(spec, collection).with_overrides(quoted=quoted)
    return render(build_report(collection.records, resolved, collection.problems), fmt)


__all__ = [
    "Collection",
    "Problem",
    "Report",
    "ReportSpec",
    "RunRecord",
    "build_report",
    "collect",
    "load",
    "make_report",
    "make_tables",
    "render",
    "resolve_spec",
]
