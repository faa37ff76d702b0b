"""Reliability diagrams: how well the predicted P(right) of accepted fixes matches how often
they were right."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.viz.axes import save_figure


def plot_reliability(calibration: dict, out: Path, title: str) -> Path:
    """Reliability diagram of equal-count bins (:func:`orthonav.bench.calibration.calibration_table`):
    left, each bin's mean predicted P(right) against its observed rate of right poses, with the
    95 % interval of that rate, the diagonal and the +- tolerance band; right, each bin's gap
    (observed - predicted) with its P range and count, where bins crowded near P = 1 on the
    left stand apart. Zoomed to the bins: accepted fixes all lie above the threshold."""
    bins, tolerance = calibration["bins"], calibration["tolerance"]
    fig, (ax, gap_ax) = plt.subplots(1, 2, figsize=(12, 5.5), gridspec_kw={"wspace": 0.35})
    low = max(0.0, min([min(b["p_low"], b["observed_low"]) for b in bins] or [0.0]) - tolerance)
    line = np.array([low, 1.0])
    band = {"color": "C2", "alpha": 0.15, "label": f"within {tolerance:.0%}"}
    ax.fill_between(line, line - tolerance, line + tolerance, **band)
    ax.plot(line, line, color="0.4", lw=1, label="perfect calibration")
    gap_ax.axhspan(-tolerance, tolerance, **band)
    gap_ax.axhline(0.0, color="0.4", lw=1)
    for i, b in enumerate(bins):
        colour = "C0" if b["within"] else "C3"
        interval = [[b["observed"] - b["observed_low"]], [b["observed_high"] - b["observed"]]]
        ax.errorbar(b["predicted"], b["observed"], yerr=interval, fmt="o", color=colour, capsize=3)
        gap_ax.errorbar(i, b["gap"], yerr=interval, fmt="o", color=colour, capsize=3)
    ax.set_xlim(low, 1.0 + tolerance / 5)
    ax.set_ylim(low, 1.0 + tolerance / 5)
    ax.set_aspect("equal")
    ax.set_xlabel("predicted P(right): mean of the bin")
    ax.set_ylabel("observed rate of right poses (95 % interval)")
    ax.legend(fontsize=8, loc="upper left")
    labels = [f"{b['p_low']:.4f}-{b['p_high']:.4f}\n{b['fixes']} fixes" for b in bins]
    gap_ax.set_xticks(range(len(bins)), labels, fontsize=7, rotation=90)
    gap_ax.set_ylabel("observed - predicted (95 % interval of the observed rate)")
    gap_ax.set_xlabel("bin: its range of P and its fixes")
    within = sum(b["within"] for b in bins)
    gap_ax.set_title(f"{within} of {len(bins)} bins within {tolerance:.0%}")
    for axis in (ax, gap_ax):
        axis.grid(alpha=0.3)
    if not bins:
        ax.text(0.5, 0.5, "no accepted fixes", ha="center", transform=ax.transAxes)
    fig.suptitle(f"{title}: {calibration['fixes']} fixes")
    return save_figure(fig, out)
