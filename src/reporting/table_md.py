"""Read back the Markdown tables that :mod:`src.reporting.render` writes (``table.md``).

For charts of sweeps whose run directories are not at hand: each ``### TITLE — METRIC (↑|↓)``
section becomes a :class:`MdTable` with its row keys, column headers and cells (mean ± std, n).
Quoted paper rows are skipped; a "–" cell is None.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

_HEADING = re.compile(r"^###\s+(?P<title>.*?)\s+—\s+(?P<metric>\S+)\s+\((?P<dir>[↑↓])\)\s*$")
_CELL = re.compile(r"^[*_]*(?P<mean>-?\d+(?:\.\d+)?)[*_]*[¹²³]?\s*(?:±\s*(?P<std>\d+(?:\.\d+)?))?\s*"
                   r"(?:\(n=(?P<n>\d+)(?:,[^)]*)?\))?$")  # fmt: skip
_FAILED = re.compile(r"^(\d+)/(\d+)$")
_EXTRA_COLUMNS = ("failed", "seed std")
_BARE_KEYS = ("experiment", "method")  # row keys shown as bare values in labels


@dataclass(frozen=True)
class Cell:
    """Mean ± sample std over n runs."""

    mean: float
    std: float
    n: int


@dataclass
class MdRow:
    keys: tuple[str, ...]
    cells: dict[str, Cell | None]
    failed: tuple[int, int] = (0, 0)


@dataclass
class MdTable:
    """One metric's table: ``key_names`` head the row-key columns, ``cols`` the value columns."""

    title: str
    metric: str
    higher_is_better: bool
    key_names: tuple[str, ...]
    cols: tuple[str, ...]
    rows: list[MdRow] = field(default_factory=list)

    def cell(self, keys: tuple[str, ...], col: str) -> Cell | None:
        for row in self.rows:
            if row.keys == keys:
                return row.cells.get(col)
        return None

    def labels(self, keys: tuple[str, ...], col: str) -> tuple[str, str, str]:
        """(scene, method, column) of a cell, as :mod:`src.reporting.chart` groups them."""
        scene, parts = "", []
        for name, value in zip(self.key_names, keys, strict=True):
            if name == "scene":
                scene = value
            else:
                parts.append(value if name in _BARE_KEYS else f"{name}={value}")
        if col.startswith("scene="):
            scene, col = col.split("=", 1)[1], ""
        return scene, " / ".join(parts), col


def parse_cell(text: str) -> Cell | None:
    """``_15.83_ ± 0.04 (n=2)`` or ``15.83³ ± 0.04 (n=2, 1 failed)`` → Cell(15.83, 0.04, 2); "–" → None."""
    m = _CELL.match(text.strip())
    if m is None:
        return None
    return Cell(float(m["mean"]), float(m["std"] or 0.0), int(m["n"] or 1))


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def parse_tables(text: str) -> list[MdTable]:
    """Every table of a ``table.md`` text, in order."""
    tables: list[MdTable] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = _HEADING.match(lines[i])
        i += 1
        if m is None:
            continue
        while i < len(lines) and not lines[i].startswith("|"):
            i += 1
        if i + 1 >= len(lines):
            break
        header, body = _cells(lines[i]), []
        i += 2  # header and separator
        while i < len(lines) and lines[i].startswith("|"):
            body.append(_cells(lines[i]))
            i += 1
        body = [r for r in body if len(r) == len(header) and "(quoted" not in r[0]]
        n_keys = next((j for j, name in enumerate(header) if "=" in name or name in _EXTRA_COLUMNS
                       or any("(n=" in r[j] for r in body)), len(header))  # fmt: skip
        cols = tuple(h for h in header[n_keys:] if h not in _EXTRA_COLUMNS)
        table = MdTable(m["title"], m["metric"], m["dir"] == "↑", tuple(header[:n_keys]), cols)
        for r in body:
            values = dict(zip(header, r, strict=True))
            failed = _FAILED.match(values.get("failed", ""))
            table.rows.append(MdRow(tuple(r[:n_keys]), {c: parse_cell(values[c]) for c in cols},
                                    (int(failed[1]), int(failed[2])) if failed else (0, 0)))  # fmt: skip
        tables.append(table)
    return tables
