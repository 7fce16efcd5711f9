"""``python -m src.bench training [--out FILE.json] [--chart FILE.png] [--quick]``: the cost of one
training iteration (``--from-json FILE.json``: the table and chart of an earlier run; ``--quick``
prints only, unless ``--out`` is given).

For each method (an experiment preset) and splat count, one subprocess (so peak memory is the
method's own) builds the model from the same configs a run uses, renders one 100 px view per step
with the rasterizer ``auto`` picks, and times :meth:`src.trainer.Trainer.train_step` split into
field (splat prediction), rasterizer (forward), backward and optimizer. Densification is off so the
splat count stays equal across methods. It also bakes the model and times rendering at 200 px, and
times the field backbone (tri-plane CNN) alone, forward + backward (``backbone_ms``).
``--head-widths`` and ``--plane-blocks`` repeat the methods with neural fields at other
``field_budget.head_width`` / ``field_budget.triplane_up_blocks`` values (the sizes a capacity search
may choose), so the SplatFields ÷ 3DGS ratio can be read per size in the same run; ``--compile
BACKEND`` repeats the methods with networks under ``trainer.compile=BACKEND`` (``first_step_ms``, the
first warm-up step, holds the compilation); ``--head-kernel on|off`` repeats them under
``model.network.head_kernel`` (``+k`` in the table: each head's layers as one AMX-BF16 kernel).
Timings are medians over the timed iterations; compare them as ratios within one run (``--repeat N``:
every row measured N times in rounds over all rows, its fastest run kept, so a spell of stolen CPU time
on a shared host does not land on one row only). ``--device
cuda`` builds the model and the view on the GPU (``rasterizer=auto`` then picks gsplat), waits for the
GPU at every timer and measures the peaks there.

The floor: each row counts the FLOPs of its networks per iteration (forward + backward of the splat
prediction, ``src.bench.flops.count_flops``; the rasterizer is not counted), ``generator_flops`` of
the tri-plane CNN alone, and divides them by the machine's matmul and conv peaks measured at the start
of the same run (``settings.peaks``): products that run under bf16 autocast (``precision`` "bf16":
the fused heads; ``generator_precision`` likewise for the CNN) at the bf16 peaks, everything else at
the float32 peaks. ``flop_floor_ms`` is
that time, ``x_flop_floor`` = ``iter_ms`` / ``flop_floor_ms``. ``split`` is a second, hook-timed
loop of the same step: generator forward, heads forward, rasterizer (forward, loss and its backward
until the splat attributes hold their gradients), heads backward (until the planes hold theirs),
generator backward, optimiser; ``generator_ms`` = generator forward + backward from that split.
The default output is ``sweeps/results/bench/training.json`` and, beside it, ``training.png``: each
row's split as a stacked bar, labelled with its × 3DGS and × floor, the floor and the 8× 3DGS target
marked (``src.bench.training_chart``).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from src.bench import load_result
from src.utils.record import OneLineParser, cli_error, os_error_line, output_file_problem, write_json

if TYPE_CHECKING:  # annotations only: the command line parses its arguments before torch loads
    import torch
    from omegaconf import DictConfig

    from src.core.cameras import Camera
    from src.data.base import View
    from src.models.base import SplatModel
    from src.optim.adam import SplatOptimizer
    from src.rasterizer.base import Rasterizer

METHODS = ("gs3d", "mip_splatting", "splatfields3d_mip", "splatfields3d_2stage", "splatfields3d", "sf_mlp",
           "deformable3dgs", "owl_4view")  # mip_splatting: also the main job's first stage
BENCH_FRAMES = 24  # frames of the shipped multi-view sequences (dynamic methods size their ResFields by it)
SIZES = (10_000, 50_000)
PARTS = ("field", "rasterizer", "backward", "optimizer")
SPLIT = ("generator_fwd", "heads_fwd", "rasterizer", "heads_bwd", "generator_bwd", "optimizer")
DEFAULT_OUT = Path("sweeps/results/bench/training.json")
# keys of a finished row that the table and the chart read (checked by --from-json)
ROW_KEYS = ("method", "n_splats", "n_params", "ms", "iter_ms", "peak_mem_mb", "fps_baked", "flops", "precision",
            "flop_floor_ms", "split", "generator_flops")


def _rss_peak_mb() -> float:
    """Peak resident set size of this process (VmHWM) in MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def measure(method: str, n_splats: int, iters: int, warmup: int, width: int, fps_width: int,
            rasterizer: str = "auto", overrides: Sequence[str] = (), device: str = "cpu") -> dict:
    """Time ``iters`` training steps of ``method`` at ``n_splats`` splats (runs in the current process).

    ``overrides``: Hydra overrides of this variant, e.g. ``field_budget.head_width=64`` (wide heads;
    narrow heads get half) or ``field_budget.triplane_up_blocks=2`` (40 px tri-planes).
    ``device``: ``cpu`` or ``cuda``; on CUDA every timer waits for the GPU (``iter_ms`` is the
    synchronised step; ``ms``, the trainer's own split, then holds launch times, and ``split`` is
    synchronised at every mark).
    """
    import torch
    from omegaconf import OmegaConf

    from src.bench.flops import device_sync
    from src.capacity import has_field
    from src.utils.memory import peak_memory_mb
    from src.utils.validate import compile_backend

    cfg, dynamic = _bench_config(method, rasterizer, device, overrides)
    dev = torch.device(device)
    sync = device_sync(dev)
    b = _bench_setup(cfg, dynamic, n_splats, width, dev)
    model = b.model
    steps = _time_steps(b, iters, warmup, sync)
    field = has_field(cfg)
    row = {"method": method, "head_width": int(cfg.field_budget.head_width) if field else None,
           "plane_blocks": _plane_blocks(cfg),
           "plane_px": getattr(model.network.backbone, "resolution", None) if field else None,
           "overrides": list(overrides), "n_splats": model.n_splats,
           "compile": compile_backend(OmegaConf.select(cfg, "trainer.compile", default=False)),
           "has_network": bool(model.networks()), "first_step_ms": steps["first_step_ms"],
           "head_kernel": bool(getattr(getattr(model, "network", None), "head_kernel", False)),
           "n_params": model.n_params(), "rasterizer": getattr(b.rasterizer, "name", type(b.rasterizer).__name__),
           "ms": steps["ms"], "iter_ms": steps["iter_ms"], "iter_ms_min": steps["iter_ms_min"], "device": dev.type}
    row["backbone_ms"] = _backbone_ms(model, iters, sync) if field else None
    row.update(_flops(model, b.view.camera, field))
    row["split"] = _split(model, b.view, b.rasterizer, b.loss_fn, b.optimizer, iters, warmup, b.background, sync)
    row["generator_ms"] = row["split"]["generator_fwd"] + row["split"]["generator_bwd"] if field else None
    row["fps_baked"] = _fps_baked(model, b.rasterizer, b.view.camera.scaled(fps_width / width), b.background, sync)
    row["peak_mem_mb"] = peak_memory_mb(dev) if dev.type == "cuda" else _rss_peak_mb()
    return row


def _bench_config(method: str, rasterizer: str, device: str, overrides: Sequence[str]) -> tuple[DictConfig, bool]:
    """(config, dynamic): the composed config of ``method`` (an experiment) with the bench's rasterizer,
    device and ``overrides``, and whether its model is dynamic.

    Time the phase that dominates training: dynamic models (``model.network.dynamic``, or a model with a
    ``warm_up``) at one of BENCH_FRAMES frames, with the deformation on (Deformable-3DGS keeps it off
    during its warm-up; the warm-up is skipped here).
    """
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    import src.run  # noqa: F401 - registers ${repo:}

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="config",
                      overrides=[f"+experiment={method}", f"rasterizer={rasterizer}", f"device={device}", *overrides])
    dynamic = bool(OmegaConf.select(cfg, "model.network.dynamic", default=False)) or "warm_up" in cfg.model
    if "warm_up" in cfg.model:
        cfg.model.warm_up = 0
    return cfg, dynamic


@dataclass
class _Bench:
    """What the timed steps run: the model, its loss, optimiser and rasterizer, one view, the background."""

    model: SplatModel
    rasterizer: Rasterizer
    loss_fn: Callable
    optimizer: SplatOptimizer
    view: View  # one ``width`` px camera looking at the splats, a random target
    background: torch.Tensor  # [3] on the model's device
    generator: torch.Generator  # the steps' draws


def _bench_setup(cfg: DictConfig, dynamic: bool, n_splats: int, width: int, dev: torch.device) -> _Bench:
    """Build ``cfg``'s model at ``n_splats`` splats on a sphere shell, its loss, optimiser and rasterizer,
    and one ``width`` px view of a random target (as the trainer does, the model is bound to it and its
    networks compiled under ``trainer.compile``)."""
    from dataclasses import replace
    from types import SimpleNamespace

    import torch
    from omegaconf import OmegaConf

    from src.core.cameras import Camera, look_at
    from src.data.base import View
    from src.trainer.trainer import Trainer
    from src.utils.instantiate import build, takes

    g = torch.Generator().manual_seed(0)
    d = torch.randn(n_splats, 3, generator=g)
    pts = d / d.norm(dim=1, keepdim=True) * (0.5 + 0.1 * torch.rand(n_splats, 1, generator=g))
    model = build(cfg.model, init=pts.to(dev), n_frames=BENCH_FRAMES if dynamic else 1).to(dev)
    rasterizer = build(cfg.rasterizer)
    extent = 4.0  # the scene extent of the learning rates and of a loss that takes one (as the trainer's fit_scene)
    loss_fn = build(cfg.loss, **takes(cfg.loss, extent=extent, generator=g))
    optimizer = build(cfg.optim)(groups=model.param_groups(), extent=extent)
    f = 0.5 * width / math.tan(0.5 * 0.69)
    w2c = look_at(torch.tensor([0.0, -4.0, 1.0]), torch.zeros(3))
    cam = Camera(w2c, f, f, width / 2, width / 2, width, width).to(dev)
    target = torch.rand(width, width, 3, generator=g).to(dev)
    if dynamic:
        cam = replace(cam, frame_id=BENCH_FRAMES // 2, time=0.5)
    view = View(camera=cam, image=target, mask=(target[..., 0] > 0.5).float(), image_id=0)
    model.bind(SimpleNamespace(train=[view]))  # as the trainer does: the 3D filters read the training cameras
    Trainer(compile=OmegaConf.select(cfg, "trainer.compile", default=False)).compile_networks(model)
    return _Bench(model, rasterizer, loss_fn, optimizer, view, torch.ones(3, device=dev), g)


def _time_steps(b: _Bench, iters: int, warmup: int, sync: Callable[[], None]) -> dict:
    """``warmup`` + ``iters`` calls of :meth:`Trainer.train_step`: ``ms`` (median per part of the timed
    ones), ``iter_ms`` / ``iter_ms_min`` (median / fastest step: the parts' sum, on CUDA the synchronised
    step) and ``first_step_ms`` (the first warm-up step, compilation included)."""
    from src.strategy.base import NoDensification
    from src.trainer.guard import DivergenceGuard
    from src.trainer.trainer import Trainer

    guard = DivergenceGuard(check_grads=False, collapse_psnr=-math.inf)
    times: dict[str, list[float]] = {k: [] for k in PARTS}
    first_step_ms = None
    synced: list[float] = []  # [iters] ms of each timed step, the GPU waited for (CUDA)
    for it in range(warmup + iters):
        sync()
        t0 = time.perf_counter()
        step = Trainer.train_step(b.model, [b.view], b.rasterizer, b.loss_fn, b.optimizer, NoDensification(), guard,
                                  it, b.generator, b.background)
        sync()
        if it == 0:
            first_step_ms = 1000 * (time.perf_counter() - t0)
        if it >= warmup:
            synced.append(1000 * (time.perf_counter() - t0))
            for k in PARTS:
                times[k].append(1000 * step["timing"][k])
    totals = synced if b.background.device.type == "cuda" else [sum(times[k][i] for k in PARTS) for i in range(iters)]
    return {"ms": {k: statistics.median(v) for k, v in times.items()}, "iter_ms": statistics.median(totals),
            "iter_ms_min": min(totals), "first_step_ms": first_step_ms}


def _fps_baked(model: SplatModel, rasterizer: Rasterizer, camera: Camera, background: torch.Tensor,
               sync: Callable[[], None], reps: int = 5) -> float:
    """Frames per second of the baked model rendered to ``camera`` (after one untimed render)."""
    import torch

    model.eval()
    with torch.no_grad():
        baked = model.bake()
        rasterizer.render(baked, camera, background)
        sync()
        t0 = time.perf_counter()
        for _ in range(reps):
            rasterizer.render(baked, camera, background)
        sync()
        return reps / (time.perf_counter() - t0)


def _flops(model, cam, field: bool) -> dict:
    """FLOPs per iteration of the networks (``flops``, ``flops_conv``, ``flops_matmul``) and of the
    generator alone (``generator_flops``, ``generator_flops_conv``), and the heads' ``precision``."""
    import torch

    from src.bench.flops import count_flops

    def networks() -> None:
        splats = model.splats_for([cam])
        loss = sum(getattr(s, k).float().sum() for s in splats for k in ("means", "scales", "quats", "opacities",
                                                                             "colors") if getattr(s, k).requires_grad)
        if torch.is_tensor(loss):
            loss.backward()
        model.zero_grad(set_to_none=True)

    def generator() -> None:
        state = model.network.backbone.prepare()
        if torch.is_tensor(state) and state.requires_grad:
            state.sum().backward()
        model.zero_grad(set_to_none=True)

    net = getattr(model, "network", None)
    kernel = bool(getattr(net, "head_kernel", False))
    if kernel:  # the counter does not see inside the AMX head kernel: count the same products layer by layer
        net.head_kernel = False
    try:
        tot = count_flops(networks)
    finally:
        if kernel:
            net.head_kernel = True
    gen = count_flops(generator) if field else {"total": 0, "conv": 0, "matmul": 0}
    bf16 = bool(getattr(net, "fused", False) and getattr(net, "autocast_bf16", False))
    gen_bf16 = bool(getattr(getattr(net, "backbone", None), "autocast_bf16", False))
    return {"generator_precision": "bf16" if gen_bf16 else "float32", "flops": tot["total"],
             "flops_conv": tot["conv"], "flops_matmul": tot["matmul"],
            "generator_flops": gen["total"], "generator_flops_conv": gen["conv"],
            "precision": "bf16" if bf16 else "float32"}


def flop_floor(row: dict, peaks: dict) -> float:
    """Milliseconds of the row's FLOPs at the measured peaks (``settings.peaks``): the heads' and the
    generator's FLOPs each at the bf16 peaks when that part runs under bf16 autocast (``precision``,
    ``generator_precision``), else at the float32 peaks."""
    from src.bench.flops import floor_ms

    gen = {"conv": row["generator_flops_conv"], "matmul": row["generator_flops"] - row["generator_flops_conv"]}
    heads = {"conv": row["flops_conv"] - gen["conv"], "matmul": row["flops_matmul"] - gen["matmul"]}
    heads_peaks = peaks["bfloat16"] if row["precision"] == "bf16" else peaks["float32"]
    gen_peaks = peaks["bfloat16"] if row.get("generator_precision") == "bf16" else peaks["float32"]
    return floor_ms(gen, gen_peaks) + floor_ms(heads, heads_peaks)


def _split(model, view, rasterizer, loss_fn, optimizer, iters: int, warmup: int, bg,
           sync: Callable[[], None] = lambda: None) -> dict[str, float]:
    """Median ms of each part of a training step (``SPLIT``), timed with autograd hooks: the
    rasterizer's backward ends when the first splat attribute receives its gradient, the heads'
    backward when the planes receive theirs. ``bg``: [3] background on the model's device. ``sync``
    runs before every mark (CUDA: the GPU's queued work is counted where it was launched)."""
    import torch

    from src.trainer.trainer import Trainer  # noqa: F401 - same import state as the timed step

    net = getattr(model, "network", None)
    backbone = getattr(net, "backbone", None)
    times: dict[str, list[float]] = {k: [] for k in SPLIT}
    cams = [view.camera]
    for it in range(warmup + iters):
        marks: dict[str, float] = {}

        def mark(name: str, marks: dict[str, float] = marks):
            def hook(grad):
                sync()
                marks.setdefault(name, time.perf_counter())
                return grad
            return hook

        optimizer.set_step(it)
        sync()
        t0 = time.perf_counter()
        state = backbone.prepare() if backbone is not None else None
        sync()
        t1 = time.perf_counter()
        splats = model.splats_for(cams, state=state) if state is not None else model.splats_for(cams)
        sync()
        t2 = time.perf_counter()
        for s in splats:
            for k in ("means", "scales", "quats", "opacities", "colors"):
                v = getattr(s, k)
                if v.requires_grad:
                    v.register_hook(mark("attrs"))
        if torch.is_tensor(state) and state.requires_grad:
            state.register_hook(mark("planes"))
        renders = [rasterizer.render(s, view.camera, bg) for s in splats]
        loss_fn(renders, [view], splats, iteration=it)["total"].backward()
        sync()
        t3 = time.perf_counter()
        optimizer.step()
        optimizer.zero_grad()
        sync()
        t4 = time.perf_counter()
        if it < warmup:
            continue
        ta = marks.get("attrs", t3)
        tp = marks.get("planes", t3)
        for k, v in (("generator_fwd", t1 - t0), ("heads_fwd", t2 - t1), ("rasterizer", ta - t2),
                     ("heads_bwd", tp - ta), ("generator_bwd", t3 - tp), ("optimizer", t4 - t3)):
            times[k].append(1000 * v)
    return {k: statistics.median(v) for k, v in times.items()}


def _backbone_ms(model, iters: int, sync: Callable[[], None] = lambda: None) -> float | None:
    """Median ms of the field backbone alone (e.g. the tri-plane CNN), forward + backward of its output
    sum: the part of a SplatFields step that does not scale with the splat count or the head width."""
    import torch

    times = []
    for _ in range(iters + 1):
        sync()
        t0 = time.perf_counter()
        state = model.network.backbone.prepare()
        tensors = [t for t in (state if isinstance(state, (list, tuple)) else [state]) if torch.is_tensor(t)]
        if not tensors or not tensors[0].requires_grad:
            return None  # a backbone without trainable state (NoBackbone)
        sum(t.sum() for t in tensors).backward()
        sync()
        times.append(1000 * (time.perf_counter() - t0))
        model.zero_grad(set_to_none=True)
    return statistics.median(times[1:])


def _plane_blocks(cfg) -> int | None:
    """The tri-plane CNN's up-sampling blocks (``n_up_blocks``), None without a CNN tri-plane."""
    from omegaconf import OmegaConf

    blocks = OmegaConf.select(cfg, "model.network.backbone.n_up_blocks", default=None)
    return int(blocks) if blocks is not None else None


def _run_isolated(method: str, n: int, args: argparse.Namespace, overrides: Sequence[str] = (),
                  variant: dict | None = None) -> dict:
    """One row, measured in a subprocess; ``variant`` (e.g. ``{"head_width": 32}``) names a failed row."""
    cmd = [sys.executable, "-m", "src.bench", "training", "--single", method, str(n), "--iters", str(args.iters),
           "--warmup", str(args.warmup), "--width", str(args.width), "--fps-width", str(args.fps_width),
           "--rasterizer", args.rasterizer, "--device", args.device]
    for o in overrides:
        cmd += ["--override-single", o]
    p = subprocess.run(cmd, capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2])
    if p.returncode != 0:
        return {"method": method, "head_width": None, "plane_blocks": None, **(variant or {}),
                "overrides": list(overrides), "n_splats": n,
                "error": p.stderr.strip().splitlines()[-1] if p.stderr else "failed"}
    return json.loads(p.stdout.strip().splitlines()[-1])


def faster_row(kept: dict, again: dict) -> dict:
    """Of two measurements of one row, the one with the shorter ``iter_ms`` (a failed one never wins);
    ``iter_ms_runs`` lists every finished measurement's ``iter_ms`` in the order they ran."""
    runs = kept.get("iter_ms_runs") or ([kept["iter_ms"]] if "error" not in kept else [])
    if "error" not in again:
        runs = [*runs, again["iter_ms"]]
    finished = [r for r in (kept, again) if "error" not in r]
    best = min(finished, key=lambda r: r["iter_ms"]) if finished else kept
    return {**best, "iter_ms_runs": runs}


def _label(r: dict) -> str:
    """``method width planes`` columns of a row (planes: the tri-plane side in px; '-' without one;
    ``+c`` after the method: its networks compiled; ``+k``: its heads as AMX kernels)."""
    planes = f"{r['plane_px']}px" if r.get("plane_px") is not None else "-"
    name = r["method"] + ("+c" if r.get("compile") else "") + ("+k" if r.get("head_kernel") else "")
    return f"{name:<19} {r.get('head_width') or '-':>5} {planes:>6}"


def print_table(rows: list[dict]) -> None:
    hdr = f"{'method':<19} {'width':>5} {'planes':>6} {'splats':>7} {'params':>9} "
    hdr += " ".join(f"{k:>10}" for k in PARTS)
    hdr += f" {'iter ms':>8} {'x 3DGS':>7} {'CNN ms':>7} {'peak MB':>8} {'FPS@200':>8}"
    hdr += f" {'GFLOP':>7} {'prec':>7} {'floor ms':>8} {'x floor':>7}"
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        if "error" in r:
            print(f"{r['method']:<19} {' '.join(r.get('overrides', []))} {r['n_splats']:>7} failed: {r['error']}")
            continue
        parts = " ".join(f"{r['ms'][k]:>10.1f}" for k in PARTS)
        ratio = f"{r['ratio_vs_gs3d']:.2f}" if r.get("ratio_vs_gs3d") else "-"
        name = _label(r)
        cnn = f"{r['backbone_ms']:.1f}" if r.get("backbone_ms") is not None else "-"
        xf = f"{r['x_flop_floor']:.2f}" if r.get("x_flop_floor") else "-"
        print(f"{name} {r['n_splats']:>7} {r['n_params']:>9} {parts} {r['iter_ms']:>8.1f} {ratio:>7} {cnn:>7} "
              f"{r['peak_mem_mb']:>8.0f} {r['fps_baked']:>8.1f} {r['flops'] / 1e9:>7.2f} {r['precision']:>7} "
              f"{r['flop_floor_ms']:>8.1f} {xf:>7}")
    print()
    hdr = f"{'split (ms)':<19} {'width':>5} {'planes':>6} {'splats':>7} " + " ".join(f"{k:>13}" for k in SPLIT)
    hdr += f" {'generator':>9} {'gen GFLOP':>9}"
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        if "error" in r:
            continue
        gen = f"{r['generator_ms']:.1f}" if r.get("generator_ms") is not None else "-"
        print(f"{_label(r)} {r['n_splats']:>7} "
              + " ".join(f"{r['split'][k]:>13.1f}" for k in SPLIT) + f" {gen:>9} {r['generator_flops'] / 1e9:>9.2f}")


def _int_list(text: str) -> list[int] | None:
    """Comma-separated integers, or None if ``text`` is not such a list."""
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        return None


def check_arguments(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse bad arguments before any work (argparse error: one line, exit code 2)."""
    methods = [m for m in args.methods.split(",") if m]
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods:
        ap.error(f"--methods: unknown method(s) {', '.join(unknown) or '(none given)'}; choose from: "
                 f"{', '.join(METHODS)}")
    sizes = _int_list(args.sizes)
    if not sizes or any(n < 1 for n in sizes):
        ap.error(f"--sizes {args.sizes!r}: expected comma-separated positive splat counts, e.g. 10000,50000")
    if args.iters < 1:
        ap.error(f"--iters {args.iters}: expected a positive number of timed iterations")
    if args.repeat < 1:
        ap.error(f"--repeat {args.repeat}: expected 1 or more measurements per row")
    if args.warmup < 0:
        ap.error(f"--warmup {args.warmup}: expected 0 or more warm-up iterations")
    if args.width < 8 or args.fps_width < 8:
        ap.error(f"--width {args.width} / --fps-width {args.fps_width}: expected at least 8 px")
    widths = _int_list(args.head_widths) if args.head_widths else []
    if widths is None or any(w < 1 for w in widths):
        ap.error(f"--head-widths {args.head_widths!r}: expected comma-separated positive widths, e.g. 64,32")
    blocks = _int_list(args.plane_blocks) if args.plane_blocks else []
    if blocks is None or any(b < 1 for b in blocks):
        ap.error(f"--plane-blocks {args.plane_blocks!r}: expected comma-separated positive up-sampling block "
                 "counts, e.g. 2,3 (2: 40 px planes, 3: 80 px)")
    if args.compile:
        from src.utils.validate import compile_backend

        try:
            compile_backend(True if args.compile == "true" else args.compile)
        except ValueError as exc:
            ap.error(f"--compile {args.compile!r}: {exc}")
    if args.head_kernel not in ("", "on", "off"):
        ap.error(f"--head-kernel {args.head_kernel!r}: choose on or off")
    if args.head_kernel == "on":
        from src.fields.head_kernel import AMX_FLAGS, cpu_has_amx

        if not cpu_has_amx():
            ap.error(f"--head-kernel on: this CPU lacks AMX-BF16 tiles (/proc/cpuinfo flags {', '.join(AMX_FLAGS)})")
    if args.rasterizer not in ("auto", "cpu", "torch_ref", "gsplat"):
        ap.error(f"--rasterizer {args.rasterizer!r}: choose from: auto, cpu, torch_ref, gsplat")
    if args.device != "cpu" and not (args.device == "cuda" or args.device.startswith("cuda:")):
        ap.error(f"--device {args.device!r}: choose cpu or cuda (cuda:N)")
    if args.device != "cpu":
        import torch

        if not torch.cuda.is_available():
            ap.error(f"--device {args.device}: no CUDA GPU on this machine")
    elif args.rasterizer == "gsplat":
        ap.error("--rasterizer gsplat needs --device cuda")


def _parser() -> OneLineParser:
    """The command line's arguments (``--help``)."""
    ap = OneLineParser(prog="python -m src.bench training", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=None,
                    help=f"write the rows as JSON here (default {DEFAULT_OUT}; --quick writes no file unless given)")
    ap.add_argument("--quick", action="store_true", help="10k splats, gs3d and splatfields3d_mip (the main job), 3 its")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--sizes", default=",".join(map(str, SIZES)))
    ap.add_argument("--iters", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--width", type=int, default=100)
    ap.add_argument("--fps-width", type=int, default=200)
    ap.add_argument("--rasterizer", default="auto", help="rasterizer config (auto, cpu, torch_ref, gsplat)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (the model, the views and the peaks on it; "
                    "timers wait for the GPU)")
    ap.add_argument("--head-widths", default="",
                    help="also time the methods with neural fields at these field_budget.head_width values, "
                         "e.g. 64,32 (the configured width is always timed)")
    ap.add_argument("--plane-blocks", default="",
                    help="also time the methods with a CNN tri-plane at these field_budget.triplane_up_blocks "
                         "values, e.g. 2,3 (40 and 80 px planes; the configured value is always timed)")
    ap.add_argument("--compile", default="", metavar="BACKEND",
                    help="also time the methods with networks under trainer.compile=BACKEND (true = inductor)")
    ap.add_argument("--head-kernel", default="", metavar="on|off",
                    help="also time the methods with neural fields under model.network.head_kernel=on|off "
                         "(each head's layers as one AMX-BF16 kernel, src/fields/head_kernel.py)")
    ap.add_argument("--repeat", type=int, default=1, metavar="N",
                    help="measure every row N times, in rounds over all rows, and keep each row's fastest run "
                         "(iter_ms_runs lists them): on a host whose speed drifts, every row sees the same spells")
    ap.add_argument("--chart", type=Path, default=None,
                    help="draw each row's split against its FLOP floor into this PNG (default: --out with .png)")
    ap.add_argument("--from-json", type=Path, default=None, metavar="FILE",
                    help="do not run: print the table and draw the chart of this earlier --out file")
    ap.add_argument("--single", nargs=2, metavar=("METHOD", "N"), help=argparse.SUPPRESS)
    ap.add_argument("--override-single", action="append", default=[], help=argparse.SUPPRESS)
    return ap


def main(argv: list[str] | None = None) -> int:
    """Command line (module docstring): 0 when every row was measured, 1 when one failed, 2 for a bad argument."""
    ap = _parser()
    args = ap.parse_args(argv)
    args.out = output_path(args.out, args.quick)
    check_outputs(ap, args)
    if args.from_json is not None:
        return _redraw(ap, args)
    check_arguments(ap, args)
    if args.single:
        print(json.dumps(measure(args.single[0], int(args.single[1]), args.iters, args.warmup, args.width,
                                 args.fps_width, args.rasterizer, args.override_single, args.device)))
        return 0
    methods = ["gs3d", "splatfields3d_mip"] if args.quick else args.methods.split(",")
    sizes = [10_000] if args.quick else [int(x) for x in args.sizes.split(",")]
    if args.quick:
        args.iters, args.warmup = 3, 1
    peaks = _peaks(args.device)
    rows = _measure_rows(methods, sizes, args)
    for r in rows:
        base = next((b for b in rows if b["method"] == "gs3d" and b["n_splats"] == r["n_splats"] and "error" not in b),
                    None)
        if base and "error" not in r:
            r["ratio_vs_gs3d"] = r["iter_ms"] / base["iter_ms"]
        if "error" not in r:
            r["flop_floor_ms"] = flop_floor(r, peaks)
            r["x_flop_floor"] = r["iter_ms"] / r["flop_floor_ms"] if r["flop_floor_ms"] > 0 else None
    print_table(rows)
    if args.out:
        result = {"rows": rows, "settings": vars(args) | {"out": str(args.out), "peaks": peaks}}
        try:
            write_json(args.out, result)
            print(f"wrote {args.out}")
            _write_chart(result, chart_path(args))
        except OSError as exc:
            return cli_error(f"cannot write the output: {os_error_line(exc)}")
    return 0 if all("error" not in r for r in rows) else 1


def _peaks(device: str) -> dict[str, dict]:
    """The matmul and conv peaks of ``device`` by dtype (``float32``, ``bfloat16``: the float32 ones where the
    CPU has no native bf16), printed."""
    import torch

    from src.bench.flops import measure_peaks
    from src.kernels.cpu import cpu_has_native_bf16

    cuda = device.startswith("cuda")
    peaks = {"float32": measure_peaks(torch.float32, device=device)}
    peaks["bfloat16"] = (measure_peaks(torch.bfloat16, device=device) if cuda or cpu_has_native_bf16()
                         else peaks["float32"])
    print("peaks GFLOP/s: " + ", ".join(f"{d} matmul {p['matmul_gflops']:.0f} conv {p['conv_gflops']:.0f}"
                                         for d, p in peaks.items()))
    return peaks


def _measure_rows(methods: list[str], sizes: list[int], args: argparse.Namespace) -> list[dict]:
    """Every row, each in its own subprocess: the methods at the sizes as configured, then the variants
    (head widths, plane blocks, compile, head kernel) of those that have the part; ``--repeat`` rounds."""
    def run(spec: tuple) -> dict:  # spec: (method, splats, overrides, variant) of one row
        return _run_isolated(spec[0], spec[1], args, spec[2], spec[3])

    specs = [(m, n, [], None) for n in sizes for m in methods]
    rows = [run(spec) for spec in specs]
    configured = list(rows)
    for key, field, values in (("head_width", "field_budget.head_width", args.head_widths),
                               ("plane_blocks", "field_budget.triplane_up_blocks", args.plane_blocks)):
        specs += [(r["method"], r["n_splats"], [f"{field}={v}"], {key: v})
                  for v in (int(x) for x in values.split(",") if x) for r in configured if r.get(key) not in (None, v)]
    if args.compile:
        specs += [(r["method"], r["n_splats"], [f"trainer.compile={args.compile}"], {"compile": args.compile})
                  for r in configured if r.get("has_network")]
    if args.head_kernel:
        specs += [(r["method"], r["n_splats"], [f"model.network.head_kernel={args.head_kernel}"],
                   {"head_kernel": args.head_kernel == "on"}) for r in configured if r.get("has_network")]
    rows += [run(spec) for spec in specs[len(rows):]]
    for _ in range(1, args.repeat):  # further rounds over all rows in the same order: drift hits every row alike
        rows = [faster_row(r, run(spec)) for r, spec in zip(rows, specs, strict=True)]
    return rows


def chart_path(args: argparse.Namespace) -> Path | None:
    """Where the chart goes: ``--chart``, else beside the JSON (``--out`` or ``--from-json``) as ``.png``."""
    beside = args.from_json if args.from_json is not None else args.out
    return args.chart or (beside.with_suffix(".png") if beside is not None else None)


def check_outputs(ap: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse an ``--out`` or chart path that cannot be written, before any work (one line, exit code 2)."""
    outputs = [("--chart", chart_path(args))]
    if args.from_json is None:
        outputs.insert(0, ("--out", args.out))
    for flag, path in outputs:
        problem = output_file_problem(path) if path is not None else None
        if problem:
            ap.error(f"{flag}: {problem}")


def output_path(out: Path | None, quick: bool) -> Path | None:
    """Where the rows go: ``out`` if given, else the kept result ``DEFAULT_OUT`` for a full run and
    nothing for ``--quick`` (a 3-iteration check must not replace the kept benchmark)."""
    if out is not None:
        return out
    return None if quick else DEFAULT_OUT


def _redraw(ap: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """``--from-json FILE``: the table and chart of an earlier result, nothing run."""
    try:
        result = load_result(args.from_json, "training benchmark result")
    except ValueError as err:
        ap.error(str(err))
    rows = result["rows"]
    for i, r in enumerate(rows):
        needed = ("method", "n_splats") if isinstance(r, dict) and "error" in r else ROW_KEYS
        missing = [k for k in needed if not isinstance(r, dict) or k not in r]
        if missing:
            ap.error(f"--from-json {args.from_json}: rows[{i}] lacks {', '.join(missing)}")
    print_table(rows)
    try:
        _write_chart(result, chart_path(args))
    except OSError as exc:
        return cli_error(f"cannot write the chart: {os_error_line(exc)}")
    return 0


def _write_chart(result: dict, path: Path) -> None:
    from src.bench.training_chart import make_training_chart

    print(f"wrote {make_training_chart(result, path)}")
