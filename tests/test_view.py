"""The splat viewer (``python -m src.view``): clear errors without a browser, and for real: the
viewer runs in a subprocess, headless Chromium opens the page and the splats' colours appear."""

from __future__ import annotations

import json
import queue
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from src.core.splats import Splats
from src.io.ply import write_ply
from src.view import ViewerError, find_run_splats, initial_view, main, viser_arrays

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]
RED, BLUE = (0.95, 0.05, 0.05), (0.05, 0.1, 0.95)


def _cluster(centre: tuple[float, float, float], rgb: tuple[float, float, float], n: int = 150,
             seed: int = 0) -> Splats:
    g = torch.Generator().manual_seed(seed)
    return Splats(means=torch.tensor(centre) + torch.randn(n, 3, generator=g) * 0.12,
                  scales=torch.full((n, 3), 0.06), quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
                  opacities=torch.full((n,), 0.95), colors=torch.tensor([rgb]).repeat(n, 1))


def _cat(*sets: Splats) -> Splats:
    return Splats(**{k: torch.cat([getattr(s, k) for s in sets]) for k in ("means", "scales", "quats", "opacities",
                                                                            "colors")})


def _static_run(root: Path) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    write_ply(root / "splats.ply", _cat(_cluster((-0.5, 0.0, 0.0), RED), _cluster((0.5, 0.0, 0.0), BLUE, seed=1)))
    (root / "metrics.json").write_text(json.dumps({"status": "ok", "method": "synthetic", "metrics": {"psnr": 30.0}}))
    return root


def _dynamic_run(root: Path) -> Path:
    """Two baked frames: a red cluster at time 0, a blue one at time 1."""
    frames = root / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    write_ply(frames / "frame_0000.ply", _cluster((0.0, 0.0, 0.0), RED))
    write_ply(frames / "frame_0001.ply", _cluster((0.0, 0.0, 0.0), BLUE, seed=1))
    index = {"frames": [{"frame_id": 0, "time": 0.0, "file": "frame_0000.ply"},
                        {"frame_id": 1, "time": 1.0, "file": "frame_0001.ply"}]}
    (frames / "frames.json").write_text(json.dumps(index))
    return root


# -- without a browser -------------------------------------------------------------------------

def test_missing_run_dir_and_missing_ply_are_named(tmp_path, capsys):
    assert main([str(tmp_path / "nope")]) == 2
    assert f"{tmp_path / 'nope'}: no such run directory" in capsys.readouterr().err
    (tmp_path / "metrics.json").write_text(json.dumps({"status": "failed"}))
    assert main([str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path}: no splats.ply and no frames/frames.json" in err and "'failed'" in err


def test_viser_missing_says_how_to_install(tmp_path, capsys, monkeypatch):
    run = _static_run(tmp_path / "run")
    monkeypatch.setitem(sys.modules, "viser", None)  # makes `import viser` raise ImportError
    assert main([str(run)]) == 1
    err = capsys.readouterr().err
    assert 'pip install -e ".[viewer]"' in err and "viser" in err


def test_malformed_ply_and_bad_frame_are_named(tmp_path, capsys):
    pytest.importorskip("viser", reason="viser not installed (pip install -e \".[viewer]\")")
    run = tmp_path / "run"
    run.mkdir()
    (run / "splats.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    assert main([str(run), "--port", "0"]) == 2
    assert f"{run / 'splats.ply'}: missing vertex property 'y'" in capsys.readouterr().err
    dyn = _dynamic_run(tmp_path / "dyn")
    assert main([str(dyn), "--frame", "7", "--port", "0"]) == 2
    assert "frames.json: no frame 7; baked frames: 0, 1" in capsys.readouterr().err
    assert main([str(_static_run(tmp_path / "static")), "--frame", "1", "--port", "0"]) == 2
    assert "--frame 1 needs per-frame PLYs" in capsys.readouterr().err


def test_a_taken_port_is_refused_in_one_line(tmp_path):
    """``--port N`` with N held by another process: one line naming the port, exit 2 (no move to N + 1)."""
    run = _static_run(tmp_path / "run")
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        p = subprocess.run([sys.executable, "-m", "src.view", str(run), "--port", str(port)], cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
    assert p.returncode == 2, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and f"--port {port}: the port is in use" in lines[0], p.stderr
    assert "Open http" not in p.stdout


def test_run_contents_and_viser_arrays(tmp_path):
    run = find_run_splats(_dynamic_run(tmp_path / "dyn"))
    assert run.dynamic and [f.frame_id for f in run.frames] == [0, 1] and run.static is None
    ply = _static_run(tmp_path / "static") / "splats.ply"
    assert find_run_splats(ply).static == ply
    with pytest.raises(ViewerError, match="not a run directory"):
        find_run_splats(tmp_path / "static" / "metrics.json")
    s = Splats(means=torch.zeros(1, 3), scales=torch.tensor([[1.0, 2.0, 3.0]]),
               quats=torch.tensor([[0.0, 0.0, 0.0, 2.0]]),  # 180 degrees about z, not unit length
               opacities=torch.tensor([0.5]), colors=torch.tensor([[1.5, 0.5, -0.1]]))
    a = viser_arrays(s)
    np.testing.assert_allclose(a["covariances"][0], np.diag([1.0, 4.0, 9.0]), atol=1e-6)
    np.testing.assert_allclose(a["rgbs"], [[1.0, 0.5, 0.0]])
    assert a["opacities"].shape == (1, 1) and a["centers"].dtype == np.float32
    pos, look = initial_view(np.random.default_rng(0).normal(size=(100, 3)))
    assert np.linalg.norm(pos - look) > 1.0 and pos[2] > look[2]  # outside the cloud, above it (+z up)


# -- in a browser --------------------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Viewer:
    """``python -m src.view`` in a subprocess; its URL is read from what it prints."""

    def __init__(self, *args: str) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "src.view", *args, "--port", str(_free_port())],
                                     cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        threading.Thread(target=self._drain, daemon=True).start()

    def _drain(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line)

    def url(self, timeout: float = 60.0) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                if self.proc.poll() is not None:
                    break
                continue
            self.output.append(line)
            m = re.search(r"Open (http://\S+) in a browser", line)
            if m:
                return m.group(1)
        raise AssertionError(f"the viewer printed no URL within {timeout} s: {''.join(self.output)}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture(scope="module")
def browser():
    pytest.importorskip("viser", reason='viser not installed (pip install -e ".[viewer-test]")')
    pytest.importorskip("playwright.sync_api", reason='playwright not installed (pip install -e ".[viewer-test]")')
    exe = CHROMIUM if Path(CHROMIUM).is_file() else shutil.which("chromium")
    if exe is None:
        pytest.skip(f"no Chromium at {CHROMIUM} or on PATH (Debian: apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS, headless=True)
        try:
            yield b
        finally:
            b.close()


def _pixels(page) -> np.ndarray:
    import io

    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB")).astype(np.int16)
    return img[200:, 60:]  # the 640 x 480 view below the GUI panels, right of the axes gizmo


def _fraction(img: np.ndarray, rgb: tuple[float, float, float]) -> float:
    """Fraction of pixels whose dominant channel is the one of ``rgb`` by a wide margin."""
    c = int(np.argmax(rgb))
    others = [i for i in range(3) if i != c]
    return float(((img[..., c] > 120) & (img[..., c] - img[..., others].max(axis=-1) > 80)).mean())


def _wait_for(page, predicate, timeout: float = 45.0) -> np.ndarray:
    """Screenshots until ``predicate(image)`` holds (the scene arrives over the websocket after the page)."""
    deadline = time.monotonic() + timeout
    img = _pixels(page)
    while not predicate(img):
        if time.monotonic() > deadline:
            raise AssertionError(f"condition not met in {timeout} s: red {_fraction(img, RED):.4f}, blue "
                                 f"{_fraction(img, BLUE):.4f}, std {img.std():.1f}")
        page.wait_for_timeout(500)
        img = _pixels(page)
    return img


def _open(browser, url: str):
    page = browser.new_page(viewport={"width": 640, "height": 480})
    page.goto(url, wait_until="load", timeout=60_000)
    page.wait_for_selector("canvas", state="attached", timeout=60_000)
    return page


@pytest.mark.slow
def test_viewer_shows_the_splats_in_a_browser(tmp_path, browser):
    viewer = _Viewer(str(_static_run(tmp_path / "run")))
    try:
        page = _open(browser, viewer.url())
        img = _wait_for(page, lambda im: _fraction(im, RED) > 0.003 and _fraction(im, BLUE) > 0.003)
        assert img.std() > 10  # not a blank page
        assert "psnr" in page.content().lower() or "PSNR" in page.inner_text("body")
        page.close()
    finally:
        viewer.stop()


@pytest.mark.slow
def test_viewer_time_slider_switches_frames(tmp_path, browser):
    viewer = _Viewer(str(_dynamic_run(tmp_path / "run")), "--frame", "1")
    try:
        page = _open(browser, viewer.url())
        img = _wait_for(page, lambda im: _fraction(im, BLUE) > 0.003)  # --frame 1: the blue frame
        assert _fraction(img, RED) < 1e-4
        thumb = page.get_by_role("slider").first
        thumb.focus()
        page.keyboard.press("ArrowLeft")  # to frame 0: the red one
        img = _wait_for(page, lambda im: _fraction(im, RED) > 0.003 and _fraction(im, BLUE) < 1e-4)
        page.close()
    finally:
        viewer.stop()
