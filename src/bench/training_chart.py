"""Chart of a training benchmark result: where each method's iteration goes, against its floor and 3DGS.

One panel per splat count. One horizontal bar per row (method, and its head width or tri-plane size
when the run timed variants), stacked from the hook-timed ``split`` (generator forward, heads forward,
rasterizer, heads backward, generator backward, optimiser); a row without a split (a failed one) is
left empty. Each bar is labelled with its median iteration time (a grey tick: the split is timed in a
second loop, so its sum differs), its multiple of the 3DGS iteration and of its FLOP floor; a black
tick marks the floor (``flop_floor_ms``) and a dashed red line the
target of 8x the 3DGS iteration. See :mod:`src.bench.training` for the definitions. Uses
matplotlib's object API with the Agg canvas (no global backend is changed).
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure

from src.reporting.chart import save_figure

TARGET_X_GS3D = 8.0  # the target: an iteration within 8x of a 3DGS iteration at the same splat count
PART_COLORS = {  # split key -> (legend label, colour)
    "generator_fwd": ("generator fwd", "tab:purple"),
    "heads_fwd": ("heads fwd", "tab:blue"),
    "rasterizer": ("rasterizer + loss", "tab:green"),
    "heads_bwd": ("heads bwd", "tab:cyan"),
    "generator_bwd": ("generator bwd", "tab:pink"),
    "optimizer": ("optimiser", "tab:gray"),
}


def _label(row: dict) -> str:
    """The bar's name: the method, with its variant when the row is one (the overrides it was measured with)."""
    over = " ".join(row.get("overrides") or [])
    extra = [f"{row['plane_px']} px planes" if "triplane_up_blocks" in over else "",
             f"width {row['head_width']}" if "head_width" in over else "",
             f"compiled ({row['compile']})" if row.get("compile") else "",
             f"head kernel {'on' if row.get('head_kernel') else 'off'}" if "head_kernel" in over else ""]
    return " ".join([row["method"], *[e for e in extra if e]])


def make_training_chart(result: dict, path: str | Path) -> Path:
    """Write the chart of ``result`` (the JSON ``src.bench training`` writes: ``rows`` and ``settings``)
    to ``path`` (PNG, written atomically); returns the path."""
    path = Path(path)
    rows = result.get("rows") or []
    sizes = sorted({r["n_splats"] for r in rows})
    if not sizes:
        raise ValueError("the benchmark result has no rows to chart")
    n_bars = max(sum(r["n_splats"] == n for r in rows) for n in sizes)
    fig = Figure(figsize=(7.5 * len(sizes), 1.6 + 0.6 * n_bars), layout="constrained")
    axes = fig.subplots(1, len(sizes), squeeze=False)[0]
    for ax, n in zip(axes, sizes, strict=True):
        panel = [r for r in rows if r["n_splats"] == n][::-1]  # first row on top
        ys = list(range(len(panel)))
        for y, r in zip(ys, panel, strict=True):
            left = 0.0
            for key, (label, color) in PART_COLORS.items():
                ms = (r.get("split") or {}).get(key, 0.0)
                ax.barh(y, ms, left=left, color=color, height=0.6, label=label if y == 0 else None)
                left += ms
            if "error" in r:
                ax.text(0, y, " failed", va="center", fontsize=7, color="tab:red")
                continue
            ax.plot([r["iter_ms"]] * 2, [y - 0.38, y + 0.38], color="0.55", lw=1.5)
            floor = r.get("flop_floor_ms")
            if floor:
                ax.plot([floor, floor], [y - 0.38, y + 0.38], color="black", lw=1.5)
            text = f" {r['iter_ms']:.1f} ms"
            if r.get("ratio_vs_gs3d") is not None and r["method"] != "gs3d":
                text += f" · {r['ratio_vs_gs3d']:.1f}× 3DGS"
            if r.get("x_flop_floor") is not None:
                text += f" · {r['x_flop_floor']:.1f}× floor ({r.get('precision', '?')})"
            ax.text(max(left, r["iter_ms"]), y, text, va="center", fontsize=7)
        base = next((r for r in panel if r["method"] == "gs3d" and "error" not in r), None)
        if base is not None:
            ax.axvline(TARGET_X_GS3D * base["iter_ms"], color="tab:red", ls="--", lw=1,
                       label=f"target: {TARGET_X_GS3D:.0f}× 3DGS")
        ax.plot([], [], color="0.55", lw=1.5, label="median iteration")
        ax.plot([], [], color="black", lw=1.5, label="FLOP floor")
        ax.set_yticks(ys, [_label(r) for r in panel], fontsize=8)
        ax.set_xlabel("training iteration, ms (hook-timed split; label: median iteration)")
        ax.set_title(f"{n // 1000} k splats", fontsize=10)
        ax.margins(x=0.45)
        ax.grid(True, axis="x", alpha=0.25)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="outside lower center", ncol=min(len(labels), 9))
    peaks = (result.get("settings") or {}).get("peaks") or {}
    sub = ", ".join(f"{d} matmul {p['matmul_gflops']:.0f} / conv {p['conv_gflops']:.0f}" for d, p in peaks.items())
    fig.suptitle(f"Training iteration split against the FLOP floor (peaks GFLOP/s: {sub or 'not recorded'})",
                 fontsize=9)
    return save_figure(fig, path, "png", 110)
