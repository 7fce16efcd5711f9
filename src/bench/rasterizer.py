"""``python -m src.bench rasterizer``: forward+backward timings of the rasterizers on synthetic objects.

For every (image width W, splat count N) it times one full differentiable render (projection,
rasterization, a loss over colour/alpha/depth, backward to all splat parameters) of ``torch_ref``,
``cpu`` (fused C++ projection, the default), ``cpu_torch_proj`` (the same compiled rasterizer with
the torch-autograd projection, i.e. ``CpuRasterizer(projection="torch")``) and, on CUDA machines
with gsplat installed, ``gsplat``, with interleaved repetitions in one process. It also reports:

* ``proj_ms`` / ``proj_ms_min``: median / min time of the projection alone (forward + backward of
  means2d, conics and depths with fixed random output gradients) for ``torch``
  (:func:`project_splats`) and ``fused`` (:func:`project_splats_fused`), timed in the same loop;

* ``contrib_pairs``: (pixel, splat) pairs that actually blend (alpha >= 1/255, before termination),
  counted by the cpu kernel;
* ``floor_ms`` = contrib_pairs x 132 FLOP / the fp32 sgemm peak measured in the same run (2048^2
  matmul, re-measured before every row; the best of the run is used, since a busy host only ever
  lowers a measurement and a low one would inflate every floor; all samples are in the JSON): the
  time any exact rasterizer needs at peak arithmetic throughput (~42 FLOP forward + ~90 backward
  per blended pair; see docs of the CPU rasterizer study), and each time as a multiple ``x_floor``
  of it;
* ``traffic_floor_ms`` = (n_splats x 112 B + pixels x 40 B) / the memory bandwidth measured in the
  same run (best large ``Tensor.copy_``, bytes read + written; re-measured like the peak): the
  splats' differentiable parameters (means, quats, scales, opacity, colour: 14 float32) read once
  and their gradients written once, the three images (colour, alpha, depth: 5 float32 per pixel)
  written once and their gradients read once. Any rasterizer moves at least this much, whatever
  the blended pairs; ``x_bound`` = each time / max(floor_ms, traffic_floor_ms), the distance from
  the larger of the two floors (the 30x target is set on ``x_floor``);
* ``speedup_vs_ref`` (median torch_ref / median cpu) and ``grad_rel_err``, the worst
  ||g_cpu - g_ref|| / ||g_ref|| over means, scales, quats, opacities and colours.

torch_ref is skipped where its estimated time (upper-bound pairs x ns/pair, calibrated on its first
run) exceeds ``--ref-max-s`` or its autograd memory (~100 B per pair) exceeds ``--ref-max-gb``.

Two seeded synthetic scenes (``--scenes``, default both): ``cube``, the scene of the CPU rasterizer
study whose prototype times the 30x floor target was set against (:func:`synthetic_cube`: 3-20 px
splats at every width, many blended pairs per splat), and ``object`` (below: small splats on a
shell, few blended pairs per splat, so per-splat stages weigh more against the floor).

Scene ``object`` ("a trained object"): a bumpy sphere of diameter ~1 centred at the origin. 90 % of
the splats lie on its surface (normal jitter 0.01) as flat discs tangent to it: tangent scales
log-uniform in [0.005, 0.03], normal scale 0.2x; 10 % fill the interior with random orientations.
Opacities sigmoid(N(2.5, 1.5)) (mostly high: median 0.92), colours U(0, 1). The camera is at
distance 4 looking at the centre with a 0.69 rad horizontal field of view, square W x W image.
The loss is sum(color * Rc) + sum(alpha * Ra) + sum(depth * Rd) with fixed random R, backpropagated
directly (the R are fed as output gradients, so the timing holds no loss arithmetic).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from src.bench import load_result
from src.core.cameras import Camera, look_at
from src.core.splats import Splats
from src.rasterizer.base import Rasterizer
from src.rasterizer.projection import TILE, Projected, project_splats, tile_rects
from src.rasterizer.projection_cpu import project_splats_fused
from src.utils.record import OneLineParser, atomic_write_text, cli_error, os_error_line, output_file_problem

FLOPS_PER_PAIR = 132  # fwd ~42 + bwd ~90 FLOP per blended (pixel, splat) pair
BYTES_PER_SPLAT = 2 * 14 * 4  # 14 float32 parameters read, their gradients written
BYTES_PER_PIXEL = 2 * 5 * 4  # colour (3), alpha, depth written; their gradients read
ATTRS = ("means", "scales", "quats", "opacities", "colors")
FULL_SIZES = [(w, n) for w in (100, 200, 400) for n in (10_000, 50_000, 200_000)]
QUICK_SIZES = [(100, 10_000)]
# keys of a result row that format_table and the chart read (checked by --from-json)
ROW_KEYS = ("width", "n_splats", "ms", "ms_min", "floor_ms", "x_floor", "contrib_pairs", "speedup_vs_ref",
            "grad_rel_err")
PROJECTIONS: dict[str, Callable[..., Projected]] = {"torch": project_splats, "fused": project_splats_fused}


def _rotmat_to_quat(R: Tensor) -> Tensor:
    """[N, 3, 3] rotation matrices -> [N, 4] quaternions (w, x, y, z) (Shepperd-style, batched)."""
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = m00 + m11 + m22
    cands = torch.stack([tr, m00, m11, m22], dim=-1)
    k = cands.argmax(dim=-1)
    q = torch.empty(R.shape[0], 4, dtype=R.dtype)
    # case w largest
    s = torch.sqrt(torch.clamp(1 + tr, min=1e-12)) * 2
    qw = torch.stack([0.25 * s, (R[:, 2, 1] - R[:, 1, 2]) / s, (R[:, 0, 2] - R[:, 2, 0]) / s,
                      (R[:, 1, 0] - R[:, 0, 1]) / s], -1)
    s = torch.sqrt(torch.clamp(1 + m00 - m11 - m22, min=1e-12)) * 2
    qx = torch.stack([(R[:, 2, 1] - R[:, 1, 2]) / s, 0.25 * s, (R[:, 0, 1] + R[:, 1, 0]) / s,
                      (R[:, 0, 2] + R[:, 2, 0]) / s], -1)
    s = torch.sqrt(torch.clamp(1 + m11 - m00 - m22, min=1e-12)) * 2
    qy = torch.stack([(R[:, 0, 2] - R[:, 2, 0]) / s, (R[:, 0, 1] + R[:, 1, 0]) / s, 0.25 * s,
                      (R[:, 1, 2] + R[:, 2, 1]) / s], -1)
    s = torch.sqrt(torch.clamp(1 + m22 - m00 - m11, min=1e-12)) * 2
    qz = torch.stack([(R[:, 1, 0] - R[:, 0, 1]) / s, (R[:, 0, 2] + R[:, 2, 0]) / s,
                      (R[:, 1, 2] + R[:, 2, 1]) / s, 0.25 * s], -1)
    for i, cand in enumerate((qw, qx, qy, qz)):
        q[k == i] = cand[k == i]
    return q / q.norm(dim=-1, keepdim=True)


def synthetic_object(n: int, seed: int = 0) -> Splats:
    """N splats resembling a trained object of unit size (see the module docstring)."""
    g = torch.Generator().manual_seed(seed)
    n_surf = round(0.9 * n)
    n_in = n - n_surf
    d = torch.randn(n_surf, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    theta = torch.acos(d[:, 2].clamp(-1, 1))
    phi = torch.atan2(d[:, 1], d[:, 0])
    radius = 0.5 * (1 + 0.12 * torch.sin(3 * theta) * torch.cos(2 * phi))
    surf = d * (radius + 0.01 * torch.randn(n_surf, generator=g, dtype=torch.float64))[:, None]
    # tangent frame (t1, t2, normal) as rotation columns
    helper = torch.where(d[:, 2:3].abs() < 0.9, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                         torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    t1 = torch.linalg.cross(helper, d)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(d, t1)
    ang = torch.rand(n_surf, generator=g, dtype=torch.float64) * 2 * math.pi
    t1r = torch.cos(ang)[:, None] * t1 + torch.sin(ang)[:, None] * t2
    t2r = torch.linalg.cross(d, t1r)
    R = torch.stack([t1r, t2r, d], dim=-1)  # columns
    q_surf = _rotmat_to_quat(R)
    lo, hi = math.log(0.005), math.log(0.03)
    s_surf = torch.exp(torch.rand(n_surf, 2, generator=g, dtype=torch.float64) * (hi - lo) + lo)
    s_surf = torch.cat([s_surf, 0.2 * s_surf.min(dim=-1, keepdim=True).values], dim=-1)
    # interior
    u = torch.randn(n_in, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True) * (0.45 * torch.rand(n_in, 1, generator=g, dtype=torch.float64) ** (1 / 3))
    q_in = torch.randn(n_in, 4, generator=g, dtype=torch.float64)
    q_in = q_in / q_in.norm(dim=-1, keepdim=True)
    s_in = torch.exp(torch.rand(n_in, 3, generator=g, dtype=torch.float64) * (hi - lo) + lo)
    means = torch.cat([surf, u])
    quats = torch.cat([q_surf, q_in])
    scales = torch.cat([s_surf, s_in])
    opac = torch.sigmoid(2.5 + 1.5 * torch.randn(n, generator=g, dtype=torch.float64))
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    perm = torch.randperm(n, generator=g)
    return Splats(means[perm].float(), scales[perm].float(), quats[perm].float(), opac[perm].float(),
                  colors[perm].float())


def object_camera(width: int, seed: int = 0, distance: float = 4.0, fov_x: float = 0.69) -> Camera:
    """Square pinhole camera at ``distance`` looking at the origin, horizontal FoV ``fov_x``."""
    g = torch.Generator().manual_seed(1000 + seed)
    d = torch.randn(3, generator=g, dtype=torch.float64)
    eye = d / d.norm() * distance
    w2c = look_at(eye, torch.zeros(3, dtype=torch.float64)).float()
    f = width / (2 * math.tan(fov_x / 2))
    return Camera(w2c, fx=f, fy=f, cx=width / 2, cy=width / 2, width=width, height=width)


def synthetic_cube(n: int, width: int, seed: int = 0) -> Splats:
    """The CPU rasterizer study's scene (``../shared/reference/cpu_rasterizer_study.md``).

    N splats uniform in a unit cube centred at z = 2.5 in front of :func:`cube_camera`, whose 3-sigma
    pixel radius is log-uniform in [3, 20] px at every resolution (world standard deviation
    r / 3 x z / f with f = 1.1 W), anisotropy +-35 % per axis, random rotations, opacities U(0.05, 0.9),
    colours U(0, 1). Denser in blended pairs than :func:`synthetic_object`.
    """
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) - 0.5
    means[:, 2] += 2.5
    f = 1.1 * width
    r_px = torch.exp(torch.rand(n, generator=g) * (math.log(20.0) - math.log(3.0)) + math.log(3.0))
    sigma = (r_px / 3.0) * means[:, 2] / f  # [N] world standard deviation
    scales = sigma[:, None] * (1.0 + 0.35 * (2.0 * torch.rand(n, 3, generator=g) - 1.0))
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    opac = 0.05 + 0.85 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return Splats(means, scales, quats, opac, colors)


def cube_camera(width: int) -> Camera:
    """Square pinhole camera of the study: at the origin looking down +z (OpenCV), f = 1.1 W."""
    f = 1.1 * width
    return Camera(torch.eye(4), fx=f, fy=f, cx=width / 2, cy=width / 2, width=width, height=width)


SCENES: dict[str, Callable[[int, int, int], tuple[Splats, Camera]]] = {
    "object": lambda n, w, seed: (synthetic_object(n, seed=seed), object_camera(w, seed=seed)),
    "cube": lambda n, w, seed: (synthetic_cube(n, w, seed=seed), cube_camera(w)),
}


def measure_peak_gflops(n: int = 2048, reps: int = 5) -> float:
    """Best fp32 matmul throughput (GFLOP/s, FMA = 2 FLOP) with torch's threads."""
    a = torch.randn(n, n)
    b = torch.randn(n, n)
    torch.mm(a, b)
    best = math.inf
    for _ in range(reps):
        t = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best / 1e9


def measure_copy_gbps(mib: int = 256, reps: int = 5) -> float:
    """Best memory bandwidth (GB/s, bytes read + written) of a large float32 ``Tensor.copy_``
    with torch's threads."""
    src = torch.ones(mib * 2**18)
    dst = torch.empty_like(src)
    dst.copy_(src)
    best = math.inf
    for _ in range(reps):
        t = time.perf_counter()
        dst.copy_(src)
        best = min(best, time.perf_counter() - t)
    return 2 * src.numel() * 4 / best / 1e9


def ref_upper_bound_pairs(splats: Splats, cam: Camera) -> int:
    """sum over tiles of (#splats binned to the tile) x (#pixels): what torch_ref evaluates."""
    with torch.no_grad():
        proj = project_splats(splats.means, splats.quats, splats.scales, cam)
        vis = proj.visible
        rect = tile_rects(proj.means2d[vis] - 0.5, proj.radii[vis], cam.width, cam.height)
        gx = math.ceil(cam.width / TILE)
        gy = math.ceil(cam.height / TILE)
        # 2D difference array of the rects
        diff = torch.zeros(gy + 1, gx + 1, dtype=torch.int64)
        for dx, dy, sgn in ((0, 1, 1), (2, 1, -1), (0, 3, -1), (2, 3, 1)):
            idx = rect[:, dy] * (gx + 1) + rect[:, dx]
            diff.view(-1).index_add_(0, idx, torch.full_like(idx, sgn))
        cnt = diff.cumsum(0).cumsum(1)[:gy, :gx]
        wx = (cam.width - TILE * torch.arange(gx)).clamp(max=TILE)
        hy = (cam.height - TILE * torch.arange(gy)).clamp(max=TILE)
        px = hy[:, None] * wx[None, :]
        return int((cnt * px).sum())


class _Loss:
    def __init__(self, cam: Camera, channels: int, seed: int = 0) -> None:
        g = torch.Generator().manual_seed(seed)
        H, W = cam.height, cam.width
        self.rc = torch.rand(H, W, channels, generator=g)
        self.ra = torch.rand(H, W, generator=g)
        self.rd = torch.rand(H, W, generator=g) * 0.1

    def __call__(self, out) -> Tensor:
        return (out.color * self.rc).sum() + (out.alpha * self.ra).sum() + (out.depth * self.rd).sum()

    def backward(self, out) -> None:
        """Backpropagate this loss without forming it (R are its gradients w.r.t. the images)."""
        torch.autograd.backward([out.color, out.alpha, out.depth], [self.rc, self.ra, self.rd])


def _fwd_bwd(rast: Rasterizer, splats: Splats, cam: Camera, loss: _Loss, bg: Tensor,
             sync: Callable[[], None]) -> tuple[float, dict[str, Tensor]]:
    params = {k: getattr(splats, k).detach().clone().requires_grad_(True) for k in ATTRS}
    sync()
    t = time.perf_counter()
    out = rast.render(Splats(**params), cam, bg)
    loss.backward(out)
    sync()
    return time.perf_counter() - t, {k: params[k].grad for k in ATTRS}


def _proj_fwd_bwd(project: Callable[..., Projected], splats: Splats, cam: Camera,
                  out_grads: tuple[Tensor, Tensor, Tensor]) -> float:
    """Seconds for one projection forward + backward to means, quats and scales."""
    params = [getattr(splats, k).detach().clone().requires_grad_(True) for k in ("means", "quats", "scales")]
    t = time.perf_counter()
    p = project(*params, cam)
    torch.autograd.backward([p.means2d, p.conics, p.depths], list(out_grads))
    return time.perf_counter() - t


class _GsplatRasterizer(Rasterizer):
    """The gsplat backend (3DGS settings: near plane 0.2, dilation 0.3) on CUDA copies of the inputs,
    its images moved back to the CPU (only when CUDA and gsplat are available)."""

    name = "gsplat"

    def __init__(self) -> None:
        from src.rasterizer.gsplat_backend import GsplatRasterizer

        self.backend = GsplatRasterizer()

    def render(self, splats: Splats, camera: Camera, background: Tensor | None = None):
        from src.core.splats import RenderOutput

        dev = torch.device("cuda")
        bg = None if background is None else background.to(dev)
        out = self.backend.render(splats.to(device=dev), camera.to(dev), bg)
        return RenderOutput(color=out.color.cpu(), alpha=out.alpha.cpu(), depth=out.depth.cpu(),
                            means2d=torch.zeros(0), radii=torch.zeros(0))


def _rasterizers() -> dict[str, Rasterizer]:
    from src.rasterizer.cpu import CpuRasterizer
    from src.rasterizer.torch_ref import TorchRefRasterizer

    out: dict[str, Rasterizer] = {"torch_ref": TorchRefRasterizer(), "cpu": CpuRasterizer(),
                                  "cpu_torch_proj": CpuRasterizer(projection="torch")}
    if torch.cuda.is_available():
        try:
            import gsplat  # noqa: F401

            out["gsplat"] = _GsplatRasterizer()
        except ImportError:
            pass
    return out


def run(sizes: list[tuple[int, int]], reps: int = 5, ref_max_s: float = 20.0, ref_max_gb: float = 6.0,
        seed: int = 0, log: Callable[[str], None] = print, scenes: tuple[str, ...] = ("object",)) -> dict:
    """Run the benchmark over ``scenes`` (keys of :data:`SCENES`) x ``sizes``; returns the
    JSON-ready result dict (one row per scene and size, ``row["scene"]`` names the scene)."""
    for name in scenes:
        if name not in SCENES:
            raise ValueError(f"unknown scene {name!r}; choose from {sorted(SCENES)}")
    from src.rasterizer.cpu import ensure_built

    ensure_built()
    rasts = _rasterizers()
    cuda_sync = torch.cuda.synchronize if "gsplat" in rasts else (lambda: None)
    # the floors use the best peak / bandwidth measured during the run (re-measured before every
    # row): a busy host only ever lowers a measurement, and a low one would inflate the floor
    peaks = [measure_peak_gflops()]
    bws = [measure_copy_gbps()]
    log(f"fp32 sgemm peak: {peaks[0]:.1f} GFLOP/s, copy bandwidth {bws[0]:.1f} GB/s (torch threads: "
        f"{torch.get_num_threads()}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '')}; both re-measured "
        "before every row, floors use the best of the run)")
    ref = _RefBudget(max_s=ref_max_s, max_gb=ref_max_gb)
    rows = []
    for scene, (width, n) in ((sc, size) for sc in scenes for size in sizes):
        if rows:
            peaks.append(measure_peak_gflops(reps=3))
            bws.append(measure_copy_gbps(reps=3))
        row = _measure_row(scene, width, n, seed, reps, rasts, ref, cuda_sync)
        set_floors(row, max(peaks), max(bws))  # the best so far; all rows are redone at the end
        rows.append(row)
        log(_format_row(row))
    peak, gbps = max(peaks), max(bws)
    for row in rows:
        set_floors(row, peak, gbps)
    return {"peak_gflops": peak, "copy_gbps": gbps, "peak_gflops_samples": peaks, "copy_gbps_samples": bws,
            "bytes_per_splat": BYTES_PER_SPLAT,
            "bytes_per_pixel": BYTES_PER_PIXEL, "threads": torch.get_num_threads(), "flops_per_pair": FLOPS_PER_PAIR,
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", ""), "rows": rows}


@dataclass
class _RefBudget:
    """When the torch reference runs: only where its estimated time and memory stay within ``max_s`` /
    ``max_gb``, estimated from the upper bound of its evaluated pairs at ``ns_per_pair`` (a prior,
    replaced by each measured run)."""

    max_s: float
    max_gb: float
    ns_per_pair: float = 40.0

    def skipped(self, upper_bound_pairs: int) -> str | None:
        """None when the reference runs for a row of ``upper_bound_pairs``, else why not."""
        est_s = upper_bound_pairs * self.ns_per_pair * 1e-9
        est_gb = upper_bound_pairs * 100 / 1e9
        return None if est_s <= self.max_s and est_gb <= self.max_gb else f"estimated {est_s:.0f} s / {est_gb:.1f} GB"


def _measure_row(scene: str, width: int, n: int, seed: int, reps: int, rasts: dict[str, Rasterizer],
                 ref: _RefBudget, cuda_sync: Callable[[], None]) -> dict:
    """One result row (floors not set): ``n`` splats of ``scene`` at ``width`` px, every rasterizer's
    forward + backward and both projections timed ``reps`` times, the pairs counted by the CPU kernel."""
    from src.rasterizer.cpu import CpuRasterizer

    splats, cam = SCENES[scene](n, width, seed)
    loss = _Loss(cam, 3, seed=seed)
    bg = torch.zeros(3)
    counter = CpuRasterizer(count_pairs=True)
    _, g_cpu = _fwd_bwd(counter, splats, cam, loss, bg, lambda: None)
    st = counter.last_stats
    ub = ref_upper_bound_pairs(splats, cam)
    skipped = ref.skipped(ub)
    names = [k for k in rasts if k != "torch_ref"]
    if skipped is None:
        names = ["torch_ref", *names]
    g = torch.Generator().manual_seed(seed)
    out_grads = (torch.randn(n, 2, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, generator=g))
    times, proj_times, grads_ref = _time_row(names, rasts, splats, cam, loss, bg, out_grads, reps, ub, ref, cuda_sync)
    ms = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    err = None
    if grads_ref is not None:
        err = max(float((g_cpu[a] - grads_ref[a]).norm() / grads_ref[a].norm().clamp_min(1e-30)) for a in ATTRS)
    return {
        "scene": scene,
        "width": width,
        "n_splats": n,
        "ms": ms,
        "ms_min": {k: 1e3 * min(v) for k, v in times.items()},
        "speedup_vs_ref": (ms["torch_ref"] / ms["cpu"]) if "torch_ref" in ms else None,
        "proj_ms": {k: 1e3 * statistics.median(v) for k, v in proj_times.items()},
        "proj_ms_min": {k: 1e3 * min(v) for k, v in proj_times.items()},
        "pixels": cam.width * cam.height,
        "grad_rel_err": err,
        "contrib_pairs": int(st["contrib_pairs"]),
        "eval_pairs_fwd": int(st["eval_fwd"]),
        "eval_pairs_bwd": int(st["eval_bwd"]),
        "tile_pairs": int(st["tile_pairs"]),
        "ref_upper_bound_pairs": ub,
        "ref_skipped": skipped,
        "cpu_stages_ms": {k: v for k, v in rasts["cpu"].last_stats.items() if k.endswith("_ms")},  # the last timed run
    }


def _time_row(names: list[str], rasts: dict[str, Rasterizer], splats: Splats, cam: Camera, loss: _Loss, bg: Tensor,
              out_grads: tuple[Tensor, Tensor, Tensor], reps: int, ub: int, ref: _RefBudget,
              cuda_sync: Callable[[], None]) -> tuple[dict[str, list[float]], dict[str, list[float]], dict | None]:
    """(seconds per rasterizer, seconds per projection, the reference's gradients or None): one warm-up of
    each (the reference's counts, and sets ``ref.ns_per_pair``), then ``reps`` rounds over all of them
    (the reference at most 3 times, once if its first run took over 5 s)."""
    times: dict[str, list[float]] = {k: [] for k in names}
    proj_times: dict[str, list[float]] = {k: [] for k in PROJECTIONS}
    for project in PROJECTIONS.values():  # warm-up
        _proj_fwd_bwd(project, splats, cam, out_grads)
    grads_ref = None
    for k in names:  # warm-up (also the reference gradients)
        dt, grads = _fwd_bwd(rasts[k], splats, cam, loss, bg, cuda_sync)
        if k == "torch_ref":
            grads_ref = grads
            ref.ns_per_pair = max(dt / max(ub, 1) * 1e9, 1.0)
            times[k].append(dt)
    for _ in range(reps):
        for k in names:
            if k == "torch_ref" and (len(times[k]) >= max(1, min(reps, 3)) or (times[k] and times[k][0] > 5.0)):
                continue
            dt, _ = _fwd_bwd(rasts[k], splats, cam, loss, bg, cuda_sync)
            times[k].append(dt)
        for k, project in PROJECTIONS.items():
            proj_times[k].append(_proj_fwd_bwd(project, splats, cam, out_grads))
    return times, proj_times, grads_ref


def set_floors(row: dict, peak_gflops: float, copy_gbps: float) -> None:
    """Set a result row's floors and multiples from its times, blended pairs and size.

    ``floor_ms`` = contrib_pairs x FLOPS_PER_PAIR / peak; ``traffic_floor_ms`` = (n_splats x
    BYTES_PER_SPLAT + pixels x BYTES_PER_PIXEL) / bandwidth; ``x_floor`` / ``x_bound`` = each
    rasterizer's median ms / floor_ms / max(floor_ms, traffic_floor_ms).
    """
    floor_ms = row["contrib_pairs"] * FLOPS_PER_PAIR / (peak_gflops * 1e9) * 1e3
    traffic_ms = (row["n_splats"] * BYTES_PER_SPLAT + row["pixels"] * BYTES_PER_PIXEL) / (copy_gbps * 1e9) * 1e3
    bound_ms = max(floor_ms, traffic_ms)
    row["floor_ms"] = floor_ms
    row["x_floor"] = {k: v / floor_ms if floor_ms > 0 else None for k, v in row["ms"].items()}
    row["traffic_floor_ms"] = traffic_ms
    row["x_bound"] = {k: v / bound_ms if bound_ms > 0 else None for k, v in row["ms"].items()}


def _fmt(x: float | None, spec: str) -> str:
    return "-" if x is None else format(x, spec)


def _format_row(r: dict) -> str:
    ms, mn = r["ms"], r["ms_min"]
    parts = [f"{r.get('scene', 'object'):<6s} W={r['width']:<4d} N={r['n_splats']:<7d}"]
    for k in ms:
        parts.append(f"{k} {ms[k]:8.1f} ms (min {mn[k]:7.1f}, {r['x_floor'][k]:6.0f}x floor)")
    parts.append(f"speedup {_fmt(r['speedup_vs_ref'], '.0f')}x")
    parts.append("proj " + " ".join(f"{k} {v:.2f} ms" for k, v in r.get("proj_ms", {}).items()))
    parts.append(f"floor {r['floor_ms']:.3f} ms")
    if "traffic_floor_ms" in r:
        parts.append(f"traffic floor {r['traffic_floor_ms']:.3f} ms")
    parts.append(f"contrib {r['contrib_pairs'] / 1e6:.2f}M eval {r['eval_pairs_fwd'] / 1e6:.1f}M")
    parts.append(f"grad err {_fmt(r['grad_rel_err'], '.1e')}")
    return " | ".join(parts)


def format_table(result: dict) -> str:
    """Markdown table of a result dict."""
    names = []
    for r in result["rows"]:
        for k in r["ms"]:
            if k not in names:
                names.append(k)
    projs = []
    for r in result["rows"]:
        for k in r.get("proj_ms", {}):
            if k not in projs:
                projs.append(k)
    head = ["scene", "W", "N", *[f"{k} ms med (min)" for k in names], *[f"proj {k} ms med (min)" for k in projs],
            "contrib pairs", "floor ms", *[f"{k} x floor" for k in names], "traffic floor ms",
            *[f"{k} x max(floors)" for k in names], "cpu vs ref", "grad rel err"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in result["rows"]:
        cells = [r.get("scene", "object"), str(r["width"]), f"{r['n_splats'] // 1000}k"]
        for k in names:
            cells.append(f"{r['ms'][k]:.1f} ({r['ms_min'][k]:.1f})" if k in r["ms"] else "skip")
        for k in projs:
            pm, pn = r.get("proj_ms", {}), r.get("proj_ms_min", {})
            cells.append(f"{pm[k]:.2f} ({pn[k]:.2f})" if k in pm else "-")
        cells += [f"{r['contrib_pairs'] / 1e6:.2f}M", f"{r['floor_ms']:.3f}"]
        for k in names:
            cells.append(f"{r['x_floor'][k]:.0f}x" if k in r["x_floor"] else "-")
        cells.append(_fmt(r.get("traffic_floor_ms"), ".3f"))
        for k in names:
            xb = r.get("x_bound", {})
            cells.append(f"{xb[k]:.0f}x" if k in xb else "-")
        cells += [_fmt(r["speedup_vs_ref"], ".0f") + ("x" if r["speedup_vs_ref"] else ""),
                  _fmt(r["grad_rel_err"], ".1e")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# Where a full run keeps the current result: one file per question, overwritten by the next run
# (earlier results stay in git history).
RESULTS_DIR = Path(__file__).resolve().parents[2] / "sweeps" / "results" / "bench"
DEFAULT_OUT = RESULTS_DIR / "rasterizer.json"
DEFAULT_CHART = RESULTS_DIR / "rasterizer.png"


def _parser() -> OneLineParser:
    """The command line of :func:`main`."""
    p = OneLineParser(prog="python -m src.bench rasterizer", description=__doc__.split("\n")[0])
    p.add_argument("--out", help=f"write the results as JSON to this file (full run default: {DEFAULT_OUT})")
    p.add_argument("--chart", help=f"draw the times against the floors into this PNG (full run default: "
                                   f"{DEFAULT_CHART})")
    p.add_argument("--no-save", action="store_true", help="full run: print the table only, write no files")
    p.add_argument("--from-json", help="do not run: print the table (and --chart) of this earlier --out file")
    p.add_argument("--quick", action="store_true", help="only 100 px x 10k splats (smoke test)")
    p.add_argument("--reps", type=int, default=None, help="timed repetitions (default 5, quick 3)")
    p.add_argument("--ref-max-s", type=float, default=20.0, help="skip torch_ref above this estimate")
    p.add_argument("--ref-max-gb", type=float, default=6.0, help="skip torch_ref above this memory estimate")
    p.add_argument("--scenes", default="object,cube",
                   help="comma-separated synthetic scenes: object (a trained-object-like shell of "
                        "small splats), cube (the CPU rasterizer study's scene, 3-20 px splats)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=None,
                   help="torch/OpenMP threads for everything (default: torch's default)")
    return p


def check_arguments(p: OneLineParser, args: argparse.Namespace) -> None:
    """Refuse bad arguments and unwritable outputs before any work (one line, exit code 2); fills in the
    default outputs of a full run."""
    if args.reps is not None and args.reps < 1:
        p.error(f"--reps {args.reps}: expected a positive number of timed repetitions")
    if args.threads is not None and args.threads < 1:
        p.error(f"--threads {args.threads}: expected a positive thread count")
    for flag, value in (("--ref-max-s", args.ref_max_s), ("--ref-max-gb", args.ref_max_gb)):
        if not (math.isfinite(value) and value >= 0):
            p.error(f"{flag} {value}: expected a finite limit of 0 or more")
    for name in (s.strip() for s in args.scenes.split(",")):
        if name not in SCENES:
            p.error(f"--scenes: unknown scene {name!r}; choose from: {', '.join(sorted(SCENES))}")
    if not (args.quick or args.no_save or args.from_json):
        args.out = args.out or str(DEFAULT_OUT)
        args.chart = args.chart or str(DEFAULT_CHART)
    for flag, path in (("--out", args.out), ("--chart", args.chart)):
        problem = output_file_problem(path) if path else None
        if problem:
            p.error(f"{flag}: {problem}")


def read_result(p: OneLineParser, path: str) -> dict:
    """The result an earlier ``--out`` wrote, checked to hold rows with every key the table reads."""
    try:
        result = load_result(path, "rasterizer benchmark result")
    except ValueError as e:
        p.error(str(e))
    for i, r in enumerate(result["rows"]):
        missing = [k for k in ROW_KEYS if not isinstance(r, dict) or k not in r]
        if missing:
            p.error(f"--from-json {path}: rows[{i}] lacks {', '.join(missing)}")
    return result


def main(argv: list[str] | None = None) -> int:
    """CLI entry: ``python -m src.bench rasterizer [--out FILE.json] [--chart FILE.png] [--quick]``
    (or ``--from-json FILE.json [--chart FILE.png]`` to table / chart an earlier result).

    A full run writes :data:`DEFAULT_OUT` and :data:`DEFAULT_CHART` unless ``--out`` / ``--chart``
    name other files or ``--no-save`` is given; ``--quick`` and ``--from-json`` write only what
    they are told to."""
    p = _parser()
    args = p.parse_args(argv)
    check_arguments(p, args)
    if args.from_json:
        result = read_result(p, args.from_json)
        print(format_table(result))
        return _write_outputs(result, None, args.chart)
    if args.threads:
        torch.set_num_threads(args.threads)
    sizes = QUICK_SIZES if args.quick else FULL_SIZES
    reps = args.reps if args.reps is not None else (3 if args.quick else 5)
    scenes = tuple(x.strip() for x in args.scenes.split(",") if x.strip())
    result = run(sizes, reps=reps, ref_max_s=args.ref_max_s, ref_max_gb=args.ref_max_gb, seed=args.seed,
                 scenes=scenes)
    print()
    print(format_table(result))
    return _write_outputs(result, args.out, args.chart)


def _write_outputs(result: dict, out: str | None, chart: str | None) -> int:
    """Write the JSON (atomically) and the chart where asked; exit code 0, or 2 with one line if a write fails."""
    try:
        if out:
            atomic_write_text(out, json.dumps(result, indent=2))
            print(f"\nwrote {out}")
        _write_chart(result, chart)
    except OSError as exc:
        return cli_error(f"cannot write the output: {os_error_line(exc)}")
    return 0


def _write_chart(result: dict, path: str | None) -> None:
    if path:
        from src.bench.rasterizer_chart import make_rasterizer_chart

        print(f"wrote {make_rasterizer_chart(result, path)}")
