"""``autocast_bf16: auto`` takes bfloat16 only where it is native AND measured faster (src/kernels/cpu.py)."""

from __future__ import annotations

import json

import pytest

import src.kernels.cpu as cpu


@pytest.fixture
def fake_cpu(monkeypatch):
    """Replace the CPU flag and the timed speed-up with given values."""
    def setup(native: bool, speedup: float) -> None:
        monkeypatch.setattr(cpu, "cpu_has_native_bf16", lambda: native)
        monkeypatch.setattr(cpu, "bf16_speedup", lambda kind: speedup)
        cpu.bf16_pays_off.cache_clear()
    yield setup
    cpu.bf16_pays_off.cache_clear()


@pytest.mark.parametrize("native, speedup, expected", [
    (True, 2.2, True),    # bf16 dot products at twice the float32 rate: take them
    (True, 0.55, False),  # native but half as fast (no AMX, one bf16 port): float32
    (True, 1.1, False),   # within noise of float32: keep float32
    (False, 3.0, False),  # not native: never
])
def test_auto_follows_flag_and_measured_speedup(fake_cpu, caplog, native, speedup, expected):
    fake_cpu(native, speedup)
    with caplog.at_level("INFO", logger="src.kernels.cpu"):
        assert cpu.bf16_pays_off("matmul") is expected
        assert cpu.resolve_autocast_bf16("auto", "conv") is expected
    assert f"matmul products in {'bfloat16' if expected else 'float32'}" in caplog.text  # the choice is logged


def test_explicit_values_are_kept_and_bad_values_named(fake_cpu):
    fake_cpu(False, 0.5)
    assert cpu.resolve_autocast_bf16(True, "matmul") is True
    assert cpu.resolve_autocast_bf16(False, "matmul") is False
    with pytest.raises(ValueError, match="autocast_bf16 must be true, false or 'auto', got 'yes'"):
        cpu.resolve_autocast_bf16("yes", "matmul")


def test_speedup_is_measured_on_this_machine():
    for kind in ("matmul", "conv"):
        s = cpu.measure_bf16_speedup(kind, rounds=1)
        assert 0.01 < s < 100.0  # a ratio of two positive times of the same work
    with pytest.raises(ValueError, match="kind must be 'matmul' or 'conv'"):
        cpu.bf16_speedup("fft")


@pytest.fixture
def cache_home(tmp_path, monkeypatch):
    """An empty cache directory and a fresh in-process cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    cpu.bf16_speedup.cache_clear()
    yield tmp_path
    cpu.bf16_speedup.cache_clear()


def test_speedup_is_measured_once_per_machine_then_read_from_disk(cache_home, monkeypatch):
    calls = []
    monkeypatch.setattr(cpu, "measure_bf16_speedup", lambda kind: calls.append(kind) or 0.6)
    assert cpu.bf16_speedup("matmul") == 0.6 and calls == ["matmul"]
    assert cpu.speedup_cache_path() == cache_home / "splatfields" / "bf16_speedup.json"
    assert list(json.loads(cpu.speedup_cache_path().read_text()).values()) == [0.6]
    # a later process (the in-process cache cleared) does not time again: every run agrees
    cpu.bf16_speedup.cache_clear()
    monkeypatch.setattr(cpu, "measure_bf16_speedup", lambda kind: pytest.fail("measured again"))
    assert cpu.bf16_speedup("matmul") == 0.6


def test_an_unreadable_cache_is_measured_again_and_rewritten(cache_home, monkeypatch):
    cpu.speedup_cache_path().parent.mkdir(parents=True)
    cpu.speedup_cache_path().write_text("{not json")
    monkeypatch.setattr(cpu, "measure_bf16_speedup", lambda kind: 2.2)
    assert cpu.bf16_speedup("conv") == 2.2
    assert list(json.loads(cpu.speedup_cache_path().read_text()).values()) == [2.2]
