"""Resume after a hard kill: a run SIGKILLed after a checkpoint and re-run with the same command and
run dir finishes with exactly the metrics of an uninterrupted run (same seed).

What makes this exact (src/trainer/trainer.py): the checkpoint holds the model (with the splat count of
that moment), optimiser moments, densification statistics, the Python / NumPy / torch / generator RNG
states, the divergence guard's running PSNR and the timing sums; everything built before training
(scene, views, init points, network init) is recomputed from the seed, identically. Measured
difference: 0.0 dB for gs3d, gs3d_moran (+opacity reset), sf_mlp and splatfields3d, killed after the
1st, 2nd or 3rd checkpoint (same code and machine for both runs).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
ITERATIONS, CKPT_EVERY = 40, 10


def command(scene: Path, run_dir: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "src.run",
        "+experiment=gs3d",
        f"dataset.root={scene}",
        f"hydra.run.dir={run_dir}",
        "threads=1",
        "eval.save_renders=false",
        "eval.fps_repeats=0",
        "+ci=smoke",
        f"trainer.iterations={ITERATIONS}",
        f"trainer.ckpt_every={CKPT_EVERY}",
        *extra,
    ]


def kill_after_checkpoints(cmd: list[str], ckpt: Path, n: int, timeout: float = 240) -> None:
    """Start ``cmd`` and SIGKILL it as soon as its ``n``-th checkpoint has been written."""
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen: set[int] = set()  # each atomic checkpoint write replaces the file: a new inode
    deadline = time.monotonic() + timeout
    try:
        while proc.poll() is None and len(seen) < n and time.monotonic() < deadline:
            try:
                seen.add(os.stat(ckpt).st_ino)
            except FileNotFoundError:
                pass
            time.sleep(0.005)
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    assert len(seen) >= n, f"no checkpoint {n} before the process ended (exit {proc.returncode})"


@pytest.mark.slow
def test_sigkilled_run_resumes_to_identical_metrics(tmp_path):
    from tests.scenes import write_blender_scene

    scene = write_blender_scene(tmp_path / "scene", n_train=10, n_test=2, size=32)
    full, killed = tmp_path / "full", tmp_path / "killed"

    p = subprocess.run(command(scene, full), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]

    kill_after_checkpoints(command(scene, killed), killed / "checkpoint.pt", n=2)
    ck = torch.load(killed / "checkpoint.pt", map_location="cpu", weights_only=True)
    assert CKPT_EVERY - 1 <= ck["iteration"] < ITERATIONS - 1  # killed mid-training
    # a killed run's record says "running", never "ok"
    assert json.loads((killed / "metrics.json").read_text())["status"] == "running"

    p = subprocess.run(command(scene, killed), cwd=REPO, capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    assert f"resumed from {killed / 'checkpoint.pt'} at iteration {ck['iteration'] + 1}" in p.stdout + p.stderr

    a = json.loads((full / "metrics.json").read_text())
    b = json.loads((killed / "metrics.json").read_text())
    assert a["status"] == b["status"] == "ok"
    assert abs(a["metrics"]["psnr"] - b["metrics"]["psnr"]) <= 1e-6
    for key in ("ssim", "psnr_train", "n_splats", "moran_rgb", "moran_opacity", "moran_cov"):
        assert a["metrics"][key] == pytest.approx(b["metrics"][key], abs=1e-9), key
    assert b["metrics"]["iter_ms"] is not None  # timing sums carried over the kill
    assert not list(killed.glob(".*.tmp"))  # no temporary files of atomic writes left


def test_resized_state_and_densification_statistics_stay_on_the_models_device():
    """A checkpoint is read onto the CPU; a model or strategy resized or restored from it keeps its own
    device (the 'meta' device stands in for a GPU: a tensor that lands on the CPU shows)."""
    from src.models.gaussians import GaussianSplatModel
    from src.strategy.default import ADCStrategy

    model = GaussianSplatModel(torch.rand(10, 3) * 2 - 1, sh_degree=1).to("meta")
    model.load_state_dict(GaussianSplatModel(torch.rand(20, 3) * 2 - 1, sh_degree=1).state_dict())
    assert {p.device.type for p in model.parameters()} == {"meta"} and model.n_splats == 20
    strategy = ADCStrategy()
    strategy.load_state_dict({"grad_accum": torch.zeros(20), "count": torch.zeros(20)})
    strategy._ensure(20, torch.device("meta"))
    assert strategy.grad_accum.device.type == "meta" and strategy.count.device.type == "meta"
