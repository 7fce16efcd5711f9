"""Find and read run records: ``**/metrics.json`` under sweep directories, or a run archive (``runs.jsonl.gz``,
:mod:`src.reporting.archive`), and the sweep's ``report:`` block.

Only file *contents* are used. Directory names are never parsed: a run's identity comes from its
``metrics.json`` (``method``, ``choices``, ``keys``, ...). A file that cannot be used is returned as
a :class:`Problem` (path + what is wrong) instead of raising.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from src.reporting.archive import ArchiveError, is_archive, read_archive

STATUSES = ("ok", "failed", "running", "interrupted")
# Keys an "ok" record must have; failed/running records only need "status".
REQUIRED_WHEN_OK = ("method", "keys", "metrics")
# Expected types of the keys when present (None allowed for the message fields).
_TYPES: dict[str, tuple[type, ...]] = {
    "status": (str,),
    "method": (str,),
    "experiment": (str, type(None)),
    "keys": (dict,),
    "metrics": (dict,),
    "choices": (dict,),
    "overrides": (list,),
    "report": (dict, type(None)),
    "error": (str, type(None)),
    "reason": (str, type(None)),
}


class RecordError(ValueError):
    """A metrics.json or multirun.yaml that cannot be used; the message says what is wrong."""


@dataclass(frozen=True)
class RunRecord:
    """One run's ``metrics.json`` content plus where it came from.

    Attributes:
        data: the parsed JSON object (schema: see ``src/reporting/__init__.py``).
        path: the metrics.json path (``<memory>`` for records built in code).
        mtime: modification time of the file, used to pick the newest of duplicate runs.
    """

    data: Mapping[str, Any]
    path: str = "<memory>"
    mtime: float = 0.0

    @property
    def status(self) -> str:
        return str(self.data["status"])

    @property
    def metrics(self) -> Mapping[str, Any]:
        return self.data.get("metrics") or {}

    @property
    def run_dir(self) -> str:
        return str(Path(self.path).parent) if self.path != "<memory>" else self.path

    def get(self, dotted: str) -> Any:
        """The value at a dotted path (``keys.n_views``); raises KeyError naming the path if absent."""
        return resolve(self.data, dotted)

    def metric(self, name: str) -> float | None:
        """``metrics[name]`` as a finite float, or None if absent, not a number, or not finite."""
        value = self.metrics.get(name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            return None
        return float(value) if math.isfinite(value) else None

    def message(self) -> str:
        """First line of ``reason`` (divergence guard) or else ``error``; empty if neither is set."""
        for key in ("reason", "error"):
            text = self.data.get(key)
            if isinstance(text, str) and text.strip():
                return text.strip().splitlines()[0]
        return ""


@dataclass(frozen=True)
class Problem:
    """A file that was skipped or a value that could not be used, with the reason."""

    path: str
    what: str
    whole_file: bool = False  # the whole input (a run archive) could not be read, not one record or line

    def __str__(self) -> str:
        return f"{self.path}: {self.what}"


@dataclass
class Collection:
    """Everything read from the sweep directories: usable records, problems, and the report block."""

    records: list[RunRecord] = field(default_factory=list)
    problems: list[Problem] = field(default_factory=list)
    report: dict[str, Any] | None = None
    n_files: int = 0


def resolve(data: Mapping[str, Any], dotted: str) -> Any:
    """Follow a dotted path (``choices.flow``) into nested mappings; KeyError(path) if a part is missing."""
    node: Any = data
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            raise KeyError(dotted)
        node = node[part]
    return node


def validate(data: Any) -> str | None:
    """What is wrong with a parsed metrics.json object, or None if it follows the contract."""
    if not isinstance(data, dict):
        return f"top level is {type(data).__name__}, expected a JSON object"
    if "status" not in data:
        return "missing key 'status'"
    for key, types in _TYPES.items():
        if key in data and not isinstance(data[key], types):
            names = " or ".join("null" if t is type(None) else t.__name__ for t in types)
            return f"key '{key}' is {type(data[key]).__name__}, expected {names}"
    if data["status"] not in STATUSES:
        return f"status {data['status']!r} is not one of {', '.join(STATUSES)}"
    if data["status"] == "ok":
        missing = [k for k in REQUIRED_WHEN_OK if k not in data]
        if missing:
            return "status 'ok' but missing key(s) " + ", ".join(f"'{k}'" for k in missing)
    return None


def record_from_mapping(data: Mapping[str, Any], path: str = "<memory>", mtime: float = 0.0) -> RunRecord:
    """A validated :class:`RunRecord`; raises :class:`RecordError` saying what is wrong."""
    what = validate(data)
    if what is not None:
        raise RecordError(what)
    return RunRecord(data=data, path=path, mtime=mtime)


def load_record(path: Path) -> RunRecord:
    """Read and validate one metrics.json; raises :class:`RecordError` for malformed JSON or missing keys."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordError(f"cannot read: {exc}") from exc
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RecordError(f"malformed JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from exc
    return record_from_mapping(data, str(path), path.stat().st_mtime)


def find_metrics_files(sweep_dir: Path) -> list[Path]:
    """All ``metrics.json`` files below ``sweep_dir`` (any depth), sorted by path."""
    return sorted(p for p in sweep_dir.glob("**/metrics.json") if p.is_file())


def read_report_block(sweep_dir: Path) -> dict[str, Any] | None:
    """The top-level ``report:`` mapping of ``sweep_dir/multirun.yaml``; None if file or block is absent.

    Raises:
        RecordError: the YAML is malformed or ``report`` is not a mapping.
    """
    path = sweep_dir / "multirun.yaml"
    if not path.is_file():
        return None
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise RecordError(f"cannot read YAML: {_yaml_error_line(exc)}") from exc
    block = data.get("report") if isinstance(data, dict) else None
    if block is not None and not isinstance(block, dict):
        raise RecordError(f"'report' is {type(block).__name__}, expected a mapping")
    return block


def _yaml_error_line(exc: Exception) -> str:
    """A YAML (or reading) error on one line: the problem and where it is, without the quoted source."""
    if isinstance(exc, yaml.MarkedYAMLError) and exc.problem:
        mark = exc.problem_mark
        where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
        return f"{exc.problem}{where}"
    return " ".join(str(exc).split())


def collect(sweep_dirs: Sequence[str | Path]) -> Collection:
    """Read every metrics.json below the sweep directories (or every run of a run archive given in their place)
    and the first ``report:`` block found.

    The report block comes from the first ``multirun.yaml`` that has one, else from the first record
    carrying a ``report`` key. Unusable files end up in ``problems``; nothing raises for bad input.
    """
    out = Collection()
    for sweep_dir in map(Path, sweep_dirs):
        if is_archive(sweep_dir):
            _collect_archive(sweep_dir, out)
            continue
        try:
            block = read_report_block(sweep_dir)
        except RecordError as exc:
            out.problems.append(Problem(str(sweep_dir / "multirun.yaml"), str(exc)))
            block = None
        if out.report is None and block is not None:
            out.report = block
        for path in find_metrics_files(sweep_dir):
            out.n_files += 1
            try:
                out.records.append(load_record(path))
            except RecordError as exc:
                out.problems.append(Problem(str(path), str(exc)))
    if out.report is None:
        out.report = report_from_records(out.records)
    return out


def _collect_archive(path: Path, out: Collection) -> None:
    """Add the runs of one run archive to ``out`` (an unreadable file or line becomes a :class:`Problem`)."""
    try:
        runs, problems, n_lines = read_archive(path)
    except ArchiveError as exc:
        out.problems.append(Problem(str(path), str(exc), whole_file=True))
        return
    out.n_files += n_lines
    out.problems.extend(Problem(where, what) for where, what in problems)
    for run_path, mtime, data in runs:
        try:
            out.records.append(record_from_mapping(data, run_path, mtime))
        except RecordError as exc:
            out.problems.append(Problem(run_path, str(exc)))


def report_from_records(records: Iterable[RunRecord]) -> dict[str, Any] | None:
    """The ``report`` block copied into the first record that has one, or None."""
    return next((dict(r.data["report"]) for r in records if r.data.get("report")), None)
