"""The portable build of the C++ extensions (no AVX2/FMA: GCC generic vectors and libm per lane), the
one machines without AVX2 (e.g. ARM) compile. It has its own code paths (e.g. the projection's
lane-by-lane row gathers instead of the AVX2 block transposes), so it is built here with
``SPLATFIELDS_NO_AVX2=1`` in a subprocess (its own cache key) and checked with the bit-exactness and
parity tests of the default build.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# parity with torch (projection bit for bit, rasterizer images/gradients), exact depth windows and
# culling, and the depth sort
SUBSET = [
    "tests/test_projection_cpu.py::test_forward_bit_identical_hard_scenes",
    "tests/test_projection_cpu.py::test_forward_standard_scenes_and_empty",
    "tests/test_projection_cpu.py::test_grads_float32_match_torch_autograd",
    "tests/test_rasterizer_cpu.py::test_parity_random_scenes",
    "tests/test_rasterizer_cpu.py::test_parity_five_channels_nonsquare_partial_tiles",
    "tests/test_rasterizer_cpu.py::test_culling_is_exact_and_results_are_deterministic",
    "tests/test_rasterizer_cpu.py::test_lane_culling_at_a_silhouette_is_exact",
    "tests/test_rasterizer_cpu.py::test_depth_windows_are_exact",
    "tests/test_rasterizer_cpu.py::test_depth_order_is_stable_argsort",
]

CHECK = """
import sys
import pytest
from src.kernels.build import compile_flags, load_extension
assert "-mavx2" not in compile_flags(), compile_flags()
assert not load_extension().has_avx2(), "the extension was built with AVX2"
sys.exit(pytest.main(["-q", "-p", "no:cacheprovider", *sys.argv[1:]]))
"""


def test_generic_build_passes_the_parity_tests():
    env = dict(os.environ, SPLATFIELDS_NO_AVX2="1")
    proc = subprocess.run([sys.executable, "-c", CHECK, *SUBSET], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    assert " passed" in proc.stdout and "failed" not in proc.stdout, proc.stdout[-2000:]
