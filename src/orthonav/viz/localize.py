"""The localize benchmark's figures: errors as shares of all frames, and each map-and-frames
pair's fix rate."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.viz.axes import save_figure


def plot_error_cdf(
    errors_by_label: dict[str, tuple[Sequence[float], int]], out: Path, title: str, xmax_m: float = 50.0
) -> Path:
    """Share of ALL frames fixed within x metres, one curve per condition.

    Each label maps to (errors of the accepted fixes, number of frames tried): a curve's
    plateau is its fix rate, so a condition that rarely fixes cannot look accurate.
    """
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for label, (errors, frames) in errors_by_label.items():
        e = np.sort(np.asarray(errors, float))
        x = np.concatenate([[0.0], e, [xmax_m]])
        y = np.concatenate([[0.0], np.arange(1, len(e) + 1), [len(e)]]) / max(frames, 1)
        ax.step(x, y, where="post", label=f"{label} ({len(e)}/{frames} fixed)")
    ax.set_xlim(0, xmax_m)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel("position error (m)")
    ax.set_ylabel("share of frames fixed within the error")
    ax.grid(alpha=0.3)
    ax.set_title(title)
    ax.legend(fontsize=7)
    return save_figure(fig, out)


def plot_pair_matrix(panels: Mapping[str, list[dict]], out: Path, target: float = 0.9) -> Path:
    """One matrix per method (map rows, frame columns) of the share of frames whose centre was
    fixed within 10 m, coloured, and beside it the share placed there (the pose found, accepted
    or not): a pair's gap between the two is the decision's, the rest of its way to 100 % the
    placement's. ``panels``: label -> bench localize rows with ``map`` and ``frames_from``."""
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.4), squeeze=False)
    for ax, (label, rows) in zip(axes[0], panels.items(), strict=True):
        names = sorted({r["map"] for r in rows} | {r["frames_from"] for r in rows})
        index = {name: i for i, name in enumerate(names)}
        fixed = np.full((len(names), len(names)), np.nan)
        for r in rows:
            i, j = index[r["map"]], index[r["frames_from"]]
            fixed[i, j] = r["centre_within_10m"]
            text = f"{r['centre_within_10m']:.0%}\n({r['placed_centre_within_10m']:.0%})"
            weight = "bold" if r["centre_within_10m"] >= target else "normal"
            ax.text(j, i, text, ha="center", va="center", fontsize=8, weight=weight)
        ax.imshow(fixed, cmap="RdYlGn", vmin=0.0, vmax=1.0)
        short = [name.rsplit("_", 1)[-1] for name in names]
        ax.set_xticks(range(len(names)), short, rotation=45, fontsize=8)
        ax.set_yticks(range(len(names)), short, fontsize=8)
        ax.set_xlabel("frames of")
        ax.set_ylabel("map of")
        met = sum(r["centre_within_10m"] >= target for r in rows)
        ax.set_title(f"{label}: {met} of {len(rows)} pairs at {target:.0%}", fontsize=9)
    fig.suptitle("frame centre within 10 m: fixed (placed, accepted or not)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, out)
