"""Run archives: every run record behind a table or board in one file, ``runs.jsonl.gz``, kept beside it.

``python -m src.tables ... --out DIR`` (tables and ``--leaderboard`` alike) writes ``DIR/runs.jsonl.gz`` with
the records it read, and ``src.tables`` takes such a file wherever it takes a sweep directory. A board can so be
rebuilt, or extended with new sweeps, after the run directories are gone::

    python -m src.tables sweeps/results/fair_budget/4_views/runs.jsonl.gz outputs/multirun/NEW --leaderboard --out DIR

Format: gzip (no timestamp in its header: the same records give the same bytes) of UTF-8 lines, one JSON object
per run, sorted by path: ``{"path": <the metrics.json path>, "mtime": <its modification time, s>, "record":
<the metrics.json object>}``. Paths under the working directory are stored relative to it; a record read from an
archive keeps the path stored there. A run present in an archive and in a sweep directory counts once, as every
duplicate run does (:mod:`src.reporting`: an ``ok`` one wins, else the newest). Only JSON is read: nothing in an
archive runs code.
"""

from __future__ import annotations

import gzip
import io
import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any, Protocol

from src.utils.record import atomic_write_bytes

ARCHIVE_NAME = "runs.jsonl.gz"
ARCHIVE_SUFFIXES = (".jsonl.gz", ".jsonl")
SEP = "#"  # "<archive>#<stored path>": the path given to a record read from an archive


class ArchiveError(ValueError):
    """A run archive that cannot be read at all (the message says why)."""


class ArchivedRun(Protocol):
    """What an archive keeps of a run (:class:`src.reporting.collect.RunRecord` has it)."""

    path: str
    mtime: float
    data: Mapping[str, Any]


def is_archive(path: str | Path) -> bool:
    """True for a run archive's file name (``*.jsonl.gz`` or, uncompressed, ``*.jsonl``)."""
    return str(path).endswith(ARCHIVE_SUFFIXES)


def stored_path(path: str) -> str:
    """The path an archive stores for a run read from ``path``: relative to the working directory when under it;
    a run read from an archive keeps the path stored there."""
    if SEP in path:
        return path.split(SEP, 1)[1]
    try:
        return Path(path).resolve().relative_to(Path.cwd().resolve()).as_posix()
    except (ValueError, OSError):
        return Path(path).as_posix()


def archive_bytes(runs: Iterable[ArchivedRun]) -> bytes:
    """The archive of ``runs`` as gzip bytes (deterministic: sorted by path, no gzip timestamp)."""
    rows = sorted(((stored_path(r.path), r.mtime, r.data) for r in runs), key=lambda row: row[0])
    text = "".join(json.dumps({"path": p, "mtime": m, "record": d}, sort_keys=True, ensure_ascii=False) + "\n"
                   for p, m, d in rows)
    buffer = io.BytesIO()
    with gzip.GzipFile(fileobj=buffer, mode="wb", mtime=0, filename="") as gz:
        gz.write(text.encode("utf-8"))
    return buffer.getvalue()


def write_archive(runs: Iterable[ArchivedRun], out_dir: Path) -> Path:
    """Write ``out_dir/runs.jsonl.gz`` atomically (the caller holds the folder's lock); returns its path."""
    path = Path(out_dir) / ARCHIVE_NAME
    atomic_write_bytes(path, archive_bytes(runs))
    return path


def read_archive(path: Path) -> tuple[list[tuple[str, float, Any]], list[tuple[str, str]], int]:
    """One archive's runs as (path ``<archive>#<stored path>``, mtime, record object as stored), the lines that
    could not be used as (``<archive>:<line>``, what is wrong), and the number of non-empty lines.

    Raises:
        ArchiveError: the file cannot be read, decompressed or decoded.
    """
    try:
        raw = path.read_bytes()
        text = (gzip.decompress(raw) if raw[:2] == b"\x1f\x8b" else raw).decode("utf-8")
    except (OSError, EOFError, gzip.BadGzipFile, UnicodeDecodeError) as exc:
        raise ArchiveError(f"cannot read the run archive: {exc}") from exc
    runs: list[tuple[str, float, Any]] = []
    problems: list[tuple[str, str]] = []
    lines = [(i, line) for i, line in enumerate(text.splitlines(), 1) if line.strip()]
    for number, line in lines:
        where = f"{path}:{number}"
        try:
            row = json.loads(line)
        except json.JSONDecodeError as exc:
            problems.append((where, f"malformed JSON: {exc.msg} at column {exc.colno}"))
            continue
        mtime = row.get("mtime", 0.0) if isinstance(row, dict) else None
        if not isinstance(row, dict) or "record" not in row:
            problems.append((where, "expected an object with 'path', 'mtime' and 'record' (a metrics.json object)"))
        elif isinstance(mtime, bool) or not isinstance(mtime, int | float):
            problems.append((where, f"'mtime' is {type(mtime).__name__}, expected a number"))
        else:
            runs.append((f"{path}{SEP}{row.get('path') or f'line {number}'}", float(mtime), row["record"]))
    return runs, problems, len(lines)
