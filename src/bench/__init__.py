"""Benchmarks: ``python -m src.bench <subcommand> ...`` (see ``src/bench/__main__.py``)."""

from __future__ import annotations

import json
from pathlib import Path


def load_result(path: Path | str, what: str) -> dict:
    """An earlier benchmark result (``--from-json``): a JSON object with a non-empty list ``rows``.

    Raises:
        ValueError: a one-line message naming ``path`` and saying what was found instead of a ``what``.
    """
    try:
        result = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise ValueError(f"--from-json {path}: not a {what} ({exc})") from None
    if not isinstance(result, dict):
        raise ValueError(f"--from-json {path}: top level is {type(result).__name__}; expected a JSON object "
                         "with 'rows'")
    rows = result.get("rows")
    if not isinstance(rows, list) or not rows:
        raise ValueError(f"--from-json {path}: 'rows' is {type(rows).__name__} {rows!r:.40}; expected a non-empty "
                         f"list of the rows of a {what}")
    return result
