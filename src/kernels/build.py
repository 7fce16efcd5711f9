"""JIT build and loading of the C++/OpenMP CPU extensions (rasterizer and fused projection).

Two shared objects (three with the 2DGS surfel kernel, :func:`load_surfel_extension`) are compiled
with ``torch.utils.cpp_extension.load`` on first use (about 30-60 s on 2 cores in total) into a
persistent cache directory keyed by a hash of the sources, compiler flags, torch and Python versions:

    $SPLATFIELDS_EXT_DIR  or  ${XDG_CACHE_HOME:-~/.cache}/splatfields/ext
        /rasterize_cpu_<hash>/   csrc/rasterize_cpu.cpp (+ simd.h): sort, binning, compositing
        /project_cpu_<hash>/     csrc/project_cpu.cpp: EWA projection forward/backward
        /surfel_cpu_<hash>/      csrc/surfel_cpu.cpp: 2D Gaussian surfel compositing forward/backward

so later processes only load the shared objects. A kernel lock (``build.flock``, released when its
holder dies) serialises the builders of each directory, so concurrent processes (e.g. pytest-xdist
workers) build once and a builder killed mid-compile does not leave later ones waiting.
Importing this module does not build anything; call :func:`load_extension`.

The C++ side includes only light ATen headers and registers its functions with ``TORCH_LIBRARY``
/ ``TORCH_LIBRARY_FRAGMENT`` (one namespace, ``splatfields_cpu``, for both objects), which keeps
the first build near 15-30 s instead of ~1 min with ``torch/extension.h``; they are called as
``torch.ops.splatfields_cpu.<name>``.

Rasterizer flags: ``-O3 -ffast-math -fno-finite-math-only -ffp-contract=off -fopenmp`` plus
``-mavx2 -mfma`` when /proc/cpuinfo reports both (portable: never ``-march=native``;
``SPLATFIELDS_NO_AVX2=1`` forces the generic-vector build, e.g. to test it). ``-fno-finite-math-only``
keeps inf/NaN comparisons meaningful in the culling code; ``-ffp-contract=off`` makes every fused
multiply-add explicit so the forward and backward evaluate identical alphas.

Projection flags: the same without ``-ffast-math`` (strict IEEE, no reassociation, no reciprocal
rewriting of divisions, no contraction into FMAs), so the fused projection repeats the torch
projection's float operations bit for bit.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import platform
import sys
import threading
from pathlib import Path
from typing import Any

import torch

from src.kernels.cpu import user_cache_dir
from src.utils.runlock import exclusive

CSRC = Path(__file__).resolve().parents[1] / "rasterizer" / "csrc"
SOURCES = [CSRC / "rasterize_cpu.cpp"]
HEADERS = [CSRC / "simd.h"]
BASE_CFLAGS = ["-O3", "-ffast-math", "-fno-finite-math-only", "-ffp-contract=off", "-fopenmp"]
SIMD_CFLAGS = ["-mavx2", "-mfma"]
LDFLAGS = ["-fopenmp"]
# fused projection: strict IEEE (bit-identical to the torch projection), its own shared object
PROJ_SOURCES = [CSRC / "project_cpu.cpp"]
PROJ_CFLAGS = ["-O3", "-fno-fast-math", "-ffp-contract=off", "-fopenmp"]
# 2D Gaussian surfel compositing (2DGS): its own shared object, built on first use by the surfel backend only
SURFEL_SOURCES = [CSRC / "surfel_cpu.cpp"]
FIELD_CSRC = Path(__file__).resolve().parents[1] / "fields" / "csrc"
# the field ops built on any CPU with the projection's flags: name -> (source, what runs when the build fails)
FIELD_OPS = {
    "triplane_sample": (FIELD_CSRC / "triplane_sample.cpp",  # bilinear tri-plane reads (fields/triplane_sample.py)
                        "The tri-planes are then read with grid_sample."),
    "encoded_row": (FIELD_CSRC / "encoded_row.cpp",  # the heads' input row [f, PE(x)] (fields/encoded_row.py)
                    "The input rows are then concatenated by torch."),
}
# headers the field ops include (part of their build keys)
FIELD_HEADERS = [FIELD_CSRC / "bf16_round.h"]
# a field head's layers as one kernel on AMX-BF16 tiles (src/fields/head_kernel.py): built on AMX CPUs only
HEAD_SOURCES = [FIELD_CSRC / "head_amx.cpp"]
HEAD_CFLAGS = ["-O3", "-fopenmp", "-mavx512f", "-mavx512bw", "-mavx512vl", "-mavx512bf16", "-mamx-tile",
                     "-mamx-bf16"]

OPS_NAMESPACE = "splatfields_cpu"

log = logging.getLogger(__name__)

_lock = threading.Lock()
_module: Any = None
_units_loaded: set[str] = set()


def cpu_has_avx2_fma() -> bool:
    """True if this x86-64 CPU reports both the avx2 and fma flags in /proc/cpuinfo."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return False
    for line in text.splitlines():
        if line.startswith("flags"):
            flags = set(line.split(":", 1)[1].split())
            return "avx2" in flags and "fma" in flags
    return False


def compile_flags() -> list[str]:
    """The C++ flags used for this machine (``SPLATFIELDS_NO_AVX2=1`` forces the portable build)."""
    use_simd = cpu_has_avx2_fma() and os.environ.get("SPLATFIELDS_NO_AVX2", "0") in ("", "0")
    return BASE_CFLAGS + (SIMD_CFLAGS if use_simd else [])


def cache_root() -> Path:
    """Root directory of the compiled-extension cache."""
    env = os.environ.get("SPLATFIELDS_EXT_DIR")
    if env:
        return Path(env).expanduser()
    return user_cache_dir() / "ext"


def projection_compile_flags() -> list[str]:
    """The C++ flags of the fused projection on this machine (strict IEEE, see the module doc)."""
    use_simd = cpu_has_avx2_fma() and os.environ.get("SPLATFIELDS_NO_AVX2", "0") in ("", "0")
    return PROJ_CFLAGS + (SIMD_CFLAGS if use_simd else [])


def build_key(flags: list[str], sources: list[Path] | None = None) -> str:
    """Hash of the sources, flags and toolchain versions (a new key means a fresh build).

    ``sources`` defaults to the rasterizer's sources and headers.
    """
    h = hashlib.sha256()
    for path in sources if sources is not None else SOURCES + HEADERS:
        h.update(path.name.encode())
        h.update(path.read_bytes())
    h.update(" ".join(flags + LDFLAGS).encode())
    h.update(torch.__version__.encode())
    h.update(sys.version.encode())
    h.update(platform.machine().encode())
    return h.hexdigest()[:16]


def build_directory() -> Path:
    """The cache directory of the current sources and flags."""
    return cache_root() / f"rasterize_cpu_{build_key(compile_flags())}"


def _load_unit(name: str, sources: list[Path], deps: list[Path], flags: list[str], verbose: bool,
               fallback: str = "Use rasterizer=torch_ref as a slow fallback.") -> None:
    """Build (if needed) and load one shared object into the process (it registers its ops)."""
    from torch.utils import cpp_extension

    key = build_key(flags, sources + deps)
    build_dir = cache_root() / f"{name}_{key}"
    build_dir.mkdir(parents=True, exist_ok=True)
    # torch's loader takes a file baton (<build_dir>/lock) that a builder killed mid-compile leaves behind,
    # and every later process then waits for it forever. Builders here first take a kernel lock, which
    # dies with its holder; whoever holds it is the only builder, so a baton it finds is stale.
    with exclusive(build_dir / "build.flock"):
        (build_dir / "lock").unlink(missing_ok=True)
        try:
            cpp_extension.load(
                name=f"splatfields_{name}_{key}",
                sources=[str(p) for p in sources],
                extra_cflags=list(flags),  # copies: torch appends to the lists it is given
                extra_ldflags=list(LDFLAGS),
                extra_include_paths=[str(CSRC)],
                build_directory=str(build_dir),
                verbose=verbose,
                is_python_module=False,
            )
        except Exception as exc:  # compiler missing, ninja missing, compile error
            raise RuntimeError(
                f"Building the CPU extension {name} failed ({type(exc).__name__}: {exc}). "
                "It needs g++ with OpenMP and the `ninja` package; the build directory is "
                f"{build_dir}. {fallback}"
            ) from exc


def load_extension(verbose: bool = False) -> Any:
    """Compile (if needed) and load both extensions; cached per process and on disk.

    Returns:
        The ``torch.ops.splatfields_cpu`` namespace (rasterizer: ``forward``, ``backward``,
        ``fast_exp``, ``depth_order``, ``has_avx2``; projection: ``project_forward``,
        ``project_backward`` and the antialiased ``project_forward_aa``, ``project_backward_aa``).

    Raises:
        RuntimeError: if the build fails (needs a C++17 compiler with OpenMP, and ``ninja``).
    """
    global _module
    if _module is not None:
        return _module
    with _lock:
        if _module is not None:
            return _module
        _load_unit("rasterize_cpu", SOURCES, HEADERS, compile_flags(), verbose)
        _load_unit("project_cpu", PROJ_SOURCES, [], projection_compile_flags(), verbose)
        _module = getattr(torch.ops, OPS_NAMESPACE)
        return _module


def _load_once(name: str, sources: list[Path], flags: list[str], verbose: bool, fallback: str,
               deps: list[Path] | None = None) -> Any:
    """Build (if needed) and load the unit ``name`` once per process (``deps``: headers in its build key);
    returns the ops namespace."""
    if name not in _units_loaded:
        with _lock:
            if name not in _units_loaded:
                _load_unit(name, sources, deps or [], flags, verbose, fallback)
                _units_loaded.add(name)
    return getattr(torch.ops, OPS_NAMESPACE)


def load_surfel_extension(verbose: bool = False) -> Any:
    """Compile (if needed) and load the surfel extension (``csrc/surfel_cpu.cpp``, 2DGS compositing).

    Built like the fused projection (strict IEEE flags, :func:`projection_compile_flags`) into
    ``surfel_cpu_<hash>/`` of the same cache; independent of :func:`load_extension`.

    Returns:
        The ``torch.ops.splatfields_cpu`` namespace (``surfel_forward``, ``surfel_backward``).

    Raises:
        RuntimeError: if the build fails (needs a C++17 compiler with OpenMP, and ``ninja``).
    """
    return _load_once("surfel_cpu", SURFEL_SOURCES, projection_compile_flags(), verbose,
                      "Use rasterizer=torch_ref as a slow fallback.")


def load_field_op(name: str, verbose: bool = False) -> Any:
    """Compile (if needed) and load the field op ``name`` of ``FIELD_OPS`` (``src/fields/csrc/<name>.cpp``).

    Built with the fused projection's flags into ``<name>_<hash>/`` of the same cache.

    Returns:
        The ``torch.ops.splatfields_cpu`` namespace (``<name>_forward``, ``<name>_backward``).

    Raises:
        RuntimeError: if the build fails (needs a C++17 compiler with OpenMP, and ``ninja``).
    """
    source, fallback = FIELD_OPS[name]
    return _load_once(name, [source], projection_compile_flags(), verbose, fallback, FIELD_HEADERS)


@functools.cache
def field_op_ready(name: str) -> bool:
    """True when the field op ``name`` is built and loaded; a failed build warns once (its torch path then runs)."""
    try:
        load_field_op(name)
    except RuntimeError as exc:
        log.warning("the compiled field op %s is unavailable (%s)", name, exc)
        return False
    return True


def load_head_extension(verbose: bool = False) -> Any:
    """Compile (if needed) and load the AMX field-head kernel (``src/fields/csrc/head_amx.cpp``).

    Built with AVX-512-BF16 / AMX flags into ``head_amx_<hash>/`` of the same cache; call it only on a CPU
    that reports ``amx_bf16``, ``amx_tile`` and ``avx512_bf16`` (``src.fields.head_kernel.cpu_has_amx``).

    Returns:
        The ``torch.ops.splatfields_cpu`` namespace (``head_forward``, ``head_backward``,
        ``head_available``).

    Raises:
        RuntimeError: if the build fails (needs g++ >= 11 with OpenMP, and ``ninja``).
    """
    return _load_once("head_amx", HEAD_SOURCES, HEAD_CFLAGS, verbose,
                      "Set model.network.head_kernel=off to use the oneDNN layers.", FIELD_HEADERS)
