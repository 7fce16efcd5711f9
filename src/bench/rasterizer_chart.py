"""Chart of a rasterizer benchmark result: each rasterizer's time against the floors, per size.

One panel per scene. x: the (image width, splat count) sizes in run order; y: milliseconds for one
forward + backward (log scale). Drawn per rasterizer: its median time (markers, labelled with the
multiple of the blended-pairs floor for ``cpu``); and the floors of the same run: the blended-pairs
floor (``floor_ms``), the target of 30x that floor, and the memory-traffic floor
(``traffic_floor_ms``, when present). See :mod:`src.bench.rasterizer` for their definitions.
Uses matplotlib's object API with the Agg canvas (no global backend is changed).
"""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure

from src.reporting.chart import save_figure

TARGET_X_FLOOR = 30.0  # the target: within 30x of the blended-pairs floor
STYLES = {"cpu": ("o", "tab:blue"), "cpu_torch_proj": ("s", "tab:cyan"), "torch_ref": ("x", "tab:orange"),
          "gsplat": ("D", "tab:green")}


def _scenes(result: dict) -> list[str]:
    names: list[str] = []
    for r in result["rows"]:
        if r.get("scene", "object") not in names:
            names.append(r.get("scene", "object"))
    return names


def make_rasterizer_chart(result: dict, path: str | Path) -> Path:
    """Write the chart of ``result`` (the dict :func:`src.bench.rasterizer.run` returns, or its
    JSON) to ``path`` (PNG, written atomically); returns the path."""
    path = Path(path)
    scenes = _scenes(result)
    if not scenes:
        raise ValueError("the benchmark result has no rows to chart")
    fig = Figure(figsize=(6.2 * len(scenes), 4.9), layout="constrained")
    axes = fig.subplots(1, len(scenes), squeeze=False)[0]
    for ax, scene in zip(axes, scenes, strict=True):
        rows = [r for r in result["rows"] if r.get("scene", "object") == scene]
        xs = list(range(len(rows)))
        floor = [r["floor_ms"] for r in rows]
        ax.plot(xs, floor, color="0.45", ls="--", lw=1, label="blended-pairs floor")
        ax.plot(xs, [TARGET_X_FLOOR * f for f in floor], color="tab:red", ls="--", lw=1.2,
                label=f"target: {TARGET_X_FLOOR:.0f}x that floor")
        if all("traffic_floor_ms" in r for r in rows):
            ax.plot(xs, [r["traffic_floor_ms"] for r in rows], color="0.45", ls=":", lw=1.2,
                    label="memory-traffic floor")
        names: list[str] = []
        for r in rows:
            names += [k for k in r["ms"] if k not in names]
        for k in names:
            pts = [(x, r["ms"][k]) for x, r in zip(xs, rows, strict=True) if k in r["ms"]]
            marker, color = STYLES.get(k, ("v", None))
            ax.plot([p[0] for p in pts], [p[1] for p in pts], marker=marker, color=color, lw=0.8, label=k)
            if k == "cpu":
                for x, r in zip(xs, rows, strict=True):
                    xf = r["x_floor"].get("cpu")
                    if xf is not None:
                        ax.annotate(f"{xf:.0f}x", (x, r["ms"]["cpu"]), textcoords="offset points",
                                    xytext=(0, 7), ha="center", fontsize=7, color=color)
        ax.set_yscale("log")
        ax.set_xticks(xs, [f"{r['width']} px\n{r['n_splats'] // 1000}k" for r in rows], fontsize=7)
        ax.set_ylabel("forward + backward, ms (median)")
        ax.set_title(f"scene {scene}", fontsize=10)
        ax.grid(True, which="both", axis="y", alpha=0.25)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="outside lower center", ncol=len(labels))
    peak, bw = result.get("peak_gflops"), result.get("copy_gbps")
    sub = f"sgemm peak {peak:.0f} GFLOP/s" if peak else ""
    if bw:
        sub += f", copy bandwidth {bw:.1f} GB/s"
    fig.suptitle(f"Rasterizer forward + backward vs the floors ({sub}; cpu labelled with x floor)", fontsize=9)
    return save_figure(fig, path, "png", 110)
