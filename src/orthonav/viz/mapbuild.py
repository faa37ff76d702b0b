"""The map build benchmark's figure: throughput and peak memory against map size."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from orthonav.viz.axes import save_figure


def plot_mapbuild_bench(rows: list[dict], out: Path) -> Path:
    """Build throughput and peak memory against map size, one line per worker setting."""
    fig, (rate_ax, mem_ax) = plt.subplots(1, 2, figsize=(13, 4.8))
    for i, workers in enumerate(dict.fromkeys(r["workers"] for r in rows)):
        group = [r for r in rows if r["workers"] == workers]
        label = "single process" if workers == "single" else f"Dask, {workers} worker(s)"
        km2 = [r["km2"] for r in group]
        rate_ax.plot(km2, [r["km2_per_min"] for r in group], "o-", color=f"C{i}", label=label)
        mem_ax.plot(km2, [r["peak_mb"] for r in group], "o-", color=f"C{i}", label=label)
    rate_ax.set_ylabel("km^2 per minute (5 m/px imagery)")
    rate_ax.set_title("Map build throughput (ORB)")
    mem_ax.set_ylabel("peak resident memory (MB)")
    mem_ax.set_title("Peak memory of the build")
    for ax in (rate_ax, mem_ax):
        ax.set_xlabel("map area (km^2)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return save_figure(fig, out)
