"""``python -m src.view RUN_DIR [--port 8080] [--host 127.0.0.1] [--frame ID] [--up +z]``

Interactive 3D view, in the browser, of a finished run's baked splats (viser's Gaussian splat
renderer, drawn with WebGL; install it with ``pip install -r requirements-viewer-lock.txt -e ".[viewer]"``).
Reads no checkpoint and builds no model:

* ``RUN_DIR/splats.ply``: the baked splat set that ``src.run`` writes (3DGS PLY layout, see
  :mod:`src.io.ply`: log-scales, logit opacities, (w, x, y, z) quaternions, DC colours);
* ``RUN_DIR/frames/frames.json`` and ``frames/frame_<id>.ply``: a dynamic run's per-time-step splat
  sets; the viewer then shows a time slider (and a play toggle) over them.

``RUN_DIR`` may also be a single ``.ply`` file. The URL to open is printed once the server listens.
Without ``--port`` the server takes port 8080, or the first free one after it (and says which); a
``--port`` that is taken is refused. A run on another machine: ``--host 0.0.0.0`` there, or an SSH tunnel
``ssh -L 8080:localhost:8080 HOST`` and http://localhost:8080 here.
"""

from __future__ import annotations

from src.kernels.threads import configure_openmp

configure_openmp()  # before anything loads torch's OpenMP runtime (src/kernels/threads.py)

import argparse
import errno
import json
import math
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from src.core.splats import Splats
from src.fields.flows import quat_to_rotmat_wxyz
from src.io.ply import BAKED_PLY, FRAMES_DIR, FRAMES_INDEX, BakedFrame, read_baked_frames, read_ply
from src.utils.record import USAGE_ERROR, OneLineParser, cli_error, os_error_line

INSTALL_HINT = 'pip install -e ".[viewer]"'
DEFAULT_PORT = 8080  # without --port: this one, or the first free one after it
_UP = {"+x": (1.0, 0.0, 0.0), "-x": (-1.0, 0.0, 0.0), "+y": (0.0, 1.0, 0.0), "-y": (0.0, -1.0, 0.0),
       "+z": (0.0, 0.0, 1.0), "-z": (0.0, 0.0, -1.0)}


class ViewerError(RuntimeError):
    """A run directory or argument the viewer cannot use; the message names the path or the flag."""

    exit_code = USAGE_ERROR


class ViewerUnavailable(ViewerError):
    """The environment lacks the viewer (viser); the message says how to install it."""

    exit_code = 1


@dataclass
class RunSplats:
    """What a run directory offers the viewer: one static PLY, or per-frame PLYs sorted by time."""

    root: Path
    static: Path | None = None
    frames: list[BakedFrame] = field(default_factory=list)
    record: dict | None = None

    @property
    def dynamic(self) -> bool:
        """True when the run holds per-frame PLYs (the viewer shows a time slider)."""
        return bool(self.frames)


def find_run_splats(run_dir: Path | str) -> RunSplats:
    """The splat files of ``run_dir`` (a run directory or one ``.ply`` file); ViewerError naming the path if none."""
    run_dir = Path(run_dir)
    if run_dir.is_file():
        if run_dir.suffix.lower() != ".ply":
            raise ViewerError(f"{run_dir}: not a run directory or a .ply file")
        return RunSplats(root=run_dir.parent, static=run_dir)
    if not run_dir.exists():
        raise ViewerError(f"{run_dir}: no such run directory")
    if not run_dir.is_dir():
        raise ViewerError(f"{run_dir}: not a directory")
    record = None
    try:
        record = json.loads((run_dir / "metrics.json").read_text())
    except (OSError, ValueError):
        record = None
    try:
        frames = read_baked_frames(run_dir)
    except ValueError as e:
        raise ViewerError(str(e)) from e
    except OSError as e:
        raise ViewerError(os_error_line(e)) from e
    static = run_dir / BAKED_PLY
    if not frames and not static.is_file():
        status = f" (its metrics.json says status {record.get('status')!r})" if isinstance(record, dict) else ""
        raise ViewerError(
            f"{run_dir}: no {BAKED_PLY} and no {FRAMES_DIR}/{FRAMES_INDEX}{status}; a finished `python -m src.run` "
            "writes splats.ply unless its model cannot bake (view-dependent colour)")
    return RunSplats(root=run_dir, static=static if static.is_file() else None, frames=frames,
                     record=record if isinstance(record, dict) else None)


def viser_arrays(splats: Splats) -> dict[str, np.ndarray]:
    """Arrays for viser's Gaussian splats: centres [N, 3], covariances R diag(s²) Rᵀ [N, 3, 3], RGB in
    [0, 1] [N, 3] and opacities [N, 1], from activated ``splats`` (linear scales, (w, x, y, z) quaternions)."""
    s = splats.detach().to("cpu", torch.float32)
    if s.colors.shape[1] != 3:
        raise ValueError(f"the viewer shows RGB splats, got {s.colors.shape[1]} colour channels")
    rot = quat_to_rotmat_wxyz(s.quats) if s.n else torch.zeros(0, 3, 3)
    rs = rot * s.scales[:, None, :]
    cov = rs @ rs.transpose(1, 2)
    return {"centers": s.means.numpy().astype(np.float32), "covariances": cov.numpy().astype(np.float32),
            "rgbs": s.colors.clamp(0.0, 1.0).numpy().astype(np.float32),
            "opacities": s.opacities.clamp(0.0, 1.0)[:, None].numpy().astype(np.float32)}


def initial_view(means: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0),
                 fov: float = math.radians(50.0)) -> tuple[np.ndarray, np.ndarray]:
    """A camera (position, look-at point) that frames the bulk of the splat ``means`` [N, 3], seen from above."""
    if len(means) == 0:
        return np.array([3.0, -3.0, 2.0]), np.zeros(3)
    centre = np.median(means, axis=0)
    radius = float(np.percentile(np.linalg.norm(means - centre, axis=1), 95)) or 1.0
    u = np.asarray(up, dtype=np.float64)
    a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    direction = a + 0.6 * b + 0.6 * u
    direction /= np.linalg.norm(direction)
    distance = 1.15 * radius / math.sin(fov / 2)
    return centre + distance * direction, centre


def import_viser() -> Any:
    """The ``viser`` module, or ViewerError with the install command."""
    try:
        import viser
    except ImportError as e:
        raise ViewerUnavailable(f"the viewer needs viser, which is not installed ({e}); install it with: "
                                f"{INSTALL_HINT}") from e
    return viser


def bind_error(host: str, port: int) -> OSError | None:
    """Why a server cannot listen on ``host``:``port`` now (``errno.EADDRINUSE``: another process holds the
    port), or None when it can: binds every address ``host`` resolves to as the viewer's server does
    (``SO_REUSEADDR``, IPv6 sockets IPv6-only), then lets them go."""
    try:
        infos = socket.getaddrinfo(host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except OSError as e:  # socket.gaierror: a host name that does not resolve
        return e
    for family, kind, proto, _, address in infos:
        try:
            sock = socket.socket(family, kind, proto)
        except OSError:  # an address family this machine lacks: the server skips it too
            continue
        with sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if family == socket.AF_INET6:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                sock.bind(address)
            except OSError as e:
                return e
    return None


def _port_taken(host: str, port: int) -> ViewerError:
    """The refusal of a ``--port`` that another process holds."""
    return ViewerError(f"--port {port}: the port is in use on {host}; choose a free one (--port 0: any) or leave "
                       f"--port out (then the first free port from {DEFAULT_PORT})")


def _check_listen(host: str, port: int | None) -> None:
    """ViewerError when the server could not listen on ``host`` at ``port`` (None: :data:`DEFAULT_PORT` or the
    first free port after it, so only a host it cannot listen on is refused)."""
    error = bind_error(host, DEFAULT_PORT if port is None else port)
    if error is None or (port is None and error.errno == errno.EADDRINUSE):
        return
    if error.errno == errno.EADDRINUSE:
        raise _port_taken(host, port)
    raise ViewerError(f"--host {host} --port {port if port is not None else DEFAULT_PORT}: cannot listen there "
                      f"({os_error_line(error)})")


def _display_url(host: str, port: int) -> str:
    shown = "localhost" if host in ("0.0.0.0", "::", "") else host
    if ":" in shown:
        shown = f"[{shown}]"
    return f"http://{shown}:{port}"


class SplatViewer:
    """A viser server showing a run's splats; dynamic runs get a time slider and a play toggle.

    ``port``: None listens on :data:`DEFAULT_PORT` or the first free port after it; a number on that port
    only (0: any free one), ViewerError when it is taken.
    """

    def __init__(self, run: RunSplats, host: str = "127.0.0.1", port: int | None = None, frame: int | None = None,
                 up: str = "+z") -> None:
        self.run = run
        self._lock = threading.Lock()
        self._cache: dict[int, dict[str, np.ndarray]] = {}
        self._shown: int | None = None
        if frame is not None and not run.dynamic:
            raise ViewerError(f"{run.root}: --frame {frame} needs per-frame PLYs ({FRAMES_DIR}/{FRAMES_INDEX}); "
                              f"this run holds one static splat set ({run.static})")
        start = 0
        if frame is not None:
            ids = [f.frame_id for f in run.frames]
            if frame not in ids:
                raise ViewerError(f"{run.root / FRAMES_DIR / FRAMES_INDEX}: no frame {frame}; baked frames: "
                                  f"{', '.join(map(str, ids))}")
            start = ids.index(frame)
        first = self._arrays(start)  # read before anything starts: a bad file fails fast
        _check_listen(host, port)  # the server would move on to the next port, or try port after port
        viser = import_viser()
        listen = DEFAULT_PORT if port is None else port
        try:
            self.server = viser.ViserServer(host=host, port=listen, verbose=False)
        except OSError as e:
            raise ViewerError(f"--host {host} --port {listen}: cannot listen there ({os_error_line(e)})") from e
        if port and self.port != port:  # another process took the port after the check: the server moved on
            self.server.stop()
            raise _port_taken(host, port)
        self.server.scene.set_up_direction(up)
        position, look_at = initial_view(first["centers"], _UP[up])
        self.server.initial_camera.position = position
        self.server.initial_camera.look_at = look_at
        self.server.gui.add_markdown(self._summary())
        self.slider = self.play = self.label = None
        if run.dynamic:
            n = len(run.frames)
            self.label = self.server.gui.add_markdown(self._frame_text(start))
            self.slider = self.server.gui.add_slider("frame", min=0, max=max(n - 1, 0), step=1, initial_value=start)
            self.play = self.server.gui.add_checkbox("play", initial_value=False)
            self.slider.on_update(lambda _event: self.show(int(self.slider.value)))
        self.show(start)

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return self.server.get_port()

    @property
    def url(self) -> str:
        """The address to open in a browser."""
        return _display_url(self.server.get_host(), self.server.get_port())

    def _path(self, index: int) -> Path:
        if self.run.dynamic:
            return self.run.frames[index].path
        assert self.run.static is not None
        return self.run.static

    def _arrays(self, index: int) -> dict[str, np.ndarray]:
        if index not in self._cache:
            path = self._path(index)
            try:
                self._cache[index] = viser_arrays(read_ply(path).splats)
            except OSError as e:
                raise ViewerError(str(e) if str(path) in str(e) else os_error_line(e)) from e
            except ValueError as e:
                raise ViewerError(str(e) if str(path) in str(e) else f"{path}: {e}") from e
        return self._cache[index]

    def _frame_text(self, index: int) -> str:
        f = self.run.frames[index]
        return f"**frame** {f.frame_id} · **time** {f.time:.4f} · {len(self._arrays(index)['centers'])} splats"

    def _summary(self) -> str:
        lines = [f"**run** `{self.run.root}`"]
        rec = self.run.record or {}
        metrics = rec.get("metrics") or {}
        if rec.get("method"):
            lines.append(f"**method** {rec['method']}")
        if isinstance(metrics.get("psnr"), int | float):
            lines.append(f"**test PSNR** {metrics['psnr']:.2f} dB")
        if not self.run.dynamic:
            lines.append(f"**splats** {len(self._arrays(0)['centers'])} (`{self._path(0).name}`)")
        elif self.run.frames:
            lines.append(f"**frames** {len(self.run.frames)} (`{FRAMES_DIR}/`)")
        return "  \n".join(lines)

    def show(self, index: int) -> None:
        """Show frame ``index`` (position in the time-sorted frame list; 0 for a static run)."""
        with self._lock:
            if index == self._shown:
                return
            arrays = self._arrays(index)
            self.server.scene.add_gaussian_splats("/splats", **arrays)
            self._shown = index
            if self.label is not None:
                self.label.content = self._frame_text(index)

    def loop(self, fps: float = 8.0) -> None:
        """Serve until interrupted; advances the time slider while ``play`` is ticked."""
        while True:
            time.sleep(1.0 / fps)
            if self.play is not None and self.play.value and self.slider is not None:
                self.slider.value = (int(self.slider.value) + 1) % len(self.run.frames)
                self.show(int(self.slider.value))

    def stop(self) -> None:
        """Stop the server."""
        self.server.stop()


def _port(text: str) -> int:
    """``--port``: an integer in [0, 65535] (0: any free port)."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a port number; expected an integer in 0..65535") \
            from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"{port} is out of range; expected 0..65535 (0: any free port)")
    return port


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line arguments (see ``--help``); a bad one exits with one line and code 2."""
    ap = OneLineParser(prog="python -m src.view", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path, help="a run directory (with splats.ply or frames/) or a .ply file")
    ap.add_argument("--port", type=_port, default=None,
                    help=f"port to listen on, refused if taken (0 = any free one; default {DEFAULT_PORT}, or the "
                         "first free one after it)")
    ap.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: all interfaces)")
    ap.add_argument("--frame", type=int, default=None, help="frame id to show first (dynamic runs)")
    ap.add_argument("--up", choices=sorted(_UP), default="+z", help="world up axis of the scene (default +z)")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Command line: serve RUN_DIR's splats until Ctrl+C.

    Exit codes: 0 after Ctrl+C; 2 an unusable run directory, splat file or argument, a taken ``--port``
    included (one line naming it); 1 the viewer is not installed.
    """
    args = parse_args(argv)
    try:
        run = find_run_splats(args.run_dir)
        viewer = SplatViewer(run, host=args.host, port=args.port, frame=args.frame, up=args.up)
    except ViewerError as e:
        cli_error(str(e))
        return e.exit_code
    what = (f"{len(run.frames)} frames from {run.root / FRAMES_DIR}" if run.dynamic else str(run.static))
    if not run.dynamic and (run.record or {}).get("per_frame") is not None:
        what += (f" (dynamic run without {FRAMES_DIR}/{FRAMES_INDEX}: showing the splat set baked at time 0)")
    print(f"Viewing {what}", flush=True)
    if args.port is None and viewer.port != DEFAULT_PORT:
        print(f"Port {DEFAULT_PORT} is in use: listening on port {viewer.port}", flush=True)
    print(f"Open {viewer.url} in a browser (Ctrl+C stops the viewer)", flush=True)
    try:
        viewer.loop()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
