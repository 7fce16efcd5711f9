"""The run record: one ``metrics.json`` per run directory, written atomically; the atomic writer every
output file goes through, :func:`output_lock` (one writer per output folder), and the one-line errors
of the command lines that write outputs (:func:`cli_error`, :class:`OneLineParser`).

The keys are a contract read by ``src.tables`` and by scripts outside the project:
``status``, ``error``, ``reason``, ``experiment``, ``method``, ``choices``, ``overrides``, ``keys``,
``metrics`` {psnr, ssim, n_splats, n_params, train_s, iter_ms, peak_mem_mb, ...}, ``views``,
``report``, ``env``.
"""

from __future__ import annotations

import argparse
import errno
import json
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NoReturn

import torch

from src.utils.runlock import RunDirLocked, RunLock

REQUIRED_METRICS = ("psnr", "ssim", "n_splats", "n_params", "train_s", "iter_ms", "peak_mem_mb")


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, torch.Tensor):
        return _jsonable(x.tolist())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if hasattr(x, "item") and callable(x.item):
        try:
            return _jsonable(x.item())
        except (ValueError, RuntimeError):
            return str(x)
    if isinstance(x, str | int | float | bool) or x is None:
        return x
    return str(x)


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (temporary file + rename)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def write_json(path: Path | str, data: dict) -> None:
    """Atomically write ``data`` as pretty JSON (non-finite floats become null)."""
    atomic_write_text(path, json.dumps(_jsonable(data), indent=2, sort_keys=False) + "\n")


def read_json(path: Path | str) -> dict | None:
    """Read a JSON file, or None if it does not exist or is malformed."""
    try:
        with open(path) as f:
            return json.load(f)
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def git_sha() -> str:
    """The repository's HEAD commit (with ``-dirty`` if modified), or ``unknown``."""
    root = Path(__file__).resolve().parents[2]
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                             timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=5).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def env_info(device: torch.device | str) -> dict:
    """Environment block of the run record."""
    return {
        "git_sha": git_sha(),
        "torch": torch.__version__,
        "device": str(device),
        "threads": torch.get_num_threads(),
    }


def process_umask() -> int:
    """This process's file-creation mask, read without changing it where the system allows.

    Linux reports it in ``/proc/self/status`` (``Umask:``); elsewhere it is read by setting and
    restoring it, which other threads could observe for that instant.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    old = os.umask(0o022)
    os.umask(old)
    return old


def plain_file_mode(path: Path) -> int:
    """The permission bits ``open(path, "w")`` leaves on ``path``: an existing file's own, else 0o666 & ~umask."""
    try:
        return os.stat(path).st_mode & 0o7777
    except FileNotFoundError:
        return 0o666 & ~process_umask()


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write ``data`` to ``path`` via a uniquely named temporary file in the same directory and a rename.

    Readers see the old content or the new, never a part; concurrent writers never share a temporary.
    The file gets the permissions a plain ``open(path, "w")`` would give it (:func:`plain_file_mode`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    mode = plain_file_mode(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), mode)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


class OutputBusy(RuntimeError):
    """Another process is writing into this output folder; the message names the folder and its holder."""


def _lock_holder(lock: RunLock) -> str:
    """Who holds ``lock`` as its file says (``pid N on HOST``), or "another process"."""
    try:
        return lock.path.read_text(errors="replace").strip() or "another process"
    except OSError:
        return "another process"


@contextmanager
def output_lock(out_dir: Path | str, hint: str = "choose another output folder") -> Iterator[Path]:
    """Hold ``out_dir``'s lock (created with its parents if missing) while the block writes into it.

    Raises:
        OutputBusy: another process holds it; nothing was written. ``hint`` ends the message.
        OSError: ``out_dir`` is a file, cannot be created, or its lock file cannot be opened.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "a file is in the way, expected a directory", str(out_dir))
    lock = RunLock(out_dir)
    try:
        lock.acquire()
    except RunDirLocked:
        raise OutputBusy(f"{out_dir} is being written by {_lock_holder(lock)}; wait for it to finish or {hint}") \
            from None
    try:
        yield out_dir
    finally:
        lock.release()


def os_error_line(exc: OSError) -> str:
    """An OSError as one line: the path it concerns and the reason (``out/table.md: Permission denied``)."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    return f"{exc.filename}: {reason}" if exc.filename is not None else reason


USAGE_ERROR = 2  # exit code of a command line whose input (an argument, a file it names) is unusable


def cli_error(message: str) -> int:
    """Print ``error: message`` (one line) on stderr; returns :data:`USAGE_ERROR` for the caller to exit with."""
    print(f"error: {' '.join(message.split())}", file=sys.stderr)
    return USAGE_ERROR


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (``error: PROG: MESSAGE; see PROG --help``), exit code 2."""

    def error(self, message: str) -> NoReturn:
        """Print the one-line error and exit with :data:`USAGE_ERROR`."""
        cli_error(f"{self.prog}: {message}; see {self.prog} --help")
        sys.exit(USAGE_ERROR)


def output_file_problem(path: Path | str) -> str | None:
    """Why ``path`` cannot be written as a file (a directory there, a file where a folder must be, a
    folder without write permission), or None; to check an output before long work."""
    path = Path(path)
    if path.is_dir():
        return f"{path}: is a directory; expected a file name"
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        return f"{folder}: is a file; expected a folder to hold {path.name}"
    if not os.access(folder, os.W_OK | os.X_OK):
        return f"{folder}: not writable; expected a folder this user may write {path.name} into"
    return None
