"""The re-localization benchmark's figure: index recall, lost frames fixed and their time."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from orthonav.viz.axes import save_figure


def plot_relocalize_bench(rows: list[dict], recall_at: Sequence[int], out: Path) -> Path:
    """Recall of each global index method, lost frames fixed and time per lost frame by fix source
    (keypoints on the index's tiles or on every tile, dense correlation on the index's tiles, the
    cascade)."""
    fig, (recall_ax, copy_ax, fixed_ax, time_ax) = plt.subplots(1, 4, figsize=(24, 4.8))
    k = max(recall_at)
    methods = list(dict.fromkeys(r.get("index", "vlad") for r in rows))
    sources = (("index", "o", "keypoints"), ("all tiles", "s", "keypoints, every tile"))
    sources += (("correlation", "^", "correlation"), ("cascade", "D", "cascade"))
    for m, method in enumerate(methods):
        for condition, style in (("same-date", "-"), ("cross-date", "--")):
            group = [r for r in rows if r["condition"] == condition and r.get("index", "vlad") == method]
            km2 = [r["km2"] for r in group]
            label = f"{method}, {condition}"
            recall_ax.plot(
                km2, [r[f"recall@{k}"] for r in group], style, marker="o", color=f"C{m}", label=label
            )
            if f"recall@{k} any copy" in group[0]:
                copies = [r[f"recall@{k} any copy"] for r in group]
                copy_ax.plot(km2, copies, style, marker="o", color=f"C{m}", label=label)
            for s, (name, marker, what) in enumerate(sources):
                if f"ms {name}" not in group[0]:
                    continue
                every = name == "all tiles"
                color = f"C{5 if every else m + 2 * s}"
                label = f"{what}, {condition}" if every else f"{what} + {method}, {condition}"
                time_ax.plot(
                    km2, [r[f"ms {name}"] for r in group], style, marker=marker, color=color, label=label
                )
                fixed = [r[f"fixed {name}"] for r in group]
                fixed_ax.plot(km2, fixed, style, marker=marker, color=color, label=label)
    recall_ax.set_ylabel(f"share of frames: tile under the drone in the top {k}")
    recall_ax.set_title(f"Global index recall@{k} (heading and altitude only)")
    copy_ax.set_ylabel(f"share of frames: that ground (any date's block) in the top {k}")
    copy_ax.set_title(f"recall@{k}, any copy of the ground")
    fixed_ax.set_ylabel("share of lost frames fixed within 25 m")
    fixed_ax.set_title("Lost frames fixed, by fix source")
    for ax in (recall_ax, copy_ax, fixed_ax):
        ax.set_ylim(0, 1.05)
    time_ax.set_yscale("log")
    time_ax.set_ylabel("median ms per lost frame")
    time_ax.set_title("Re-localization time by fix source")
    for ax in (recall_ax, copy_ax, fixed_ax, time_ax):
        ax.set_xlabel("map area (km^2)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    return save_figure(fig, out)
