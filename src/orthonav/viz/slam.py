"""Pictures of the SLAM benchmark: trajectories of one seed and the error medians per setup."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.viz.plots import _save


def plot_slam_bench(summary: list[dict], example: dict[str, dict], out: Path) -> Path:
    """Left: UAV 1's position error along the flight per setup (seed 0); right: ATE, RPE and landmark
    error medians per setup, without (hatched) and with map fixes."""
    fig, (track_ax, err_ax) = plt.subplots(1, 2, figsize=(14, 5.5), gridspec_kw={"width_ratios": [1, 1.3]})
    for i, (label, track) in enumerate(example.items()):
        error = np.linalg.norm(np.array(track["estimate_en"]) - np.array(track["truth_en"]), axis=1)
        style = "-" if "map fixes" in label else ":"
        track_ax.plot(error, style, color=f"C{i % 4}", lw=1.5, label=label)
    track_ax.set_xlabel("keyframe (8 s, 160 m apart)")
    track_ax.set_ylabel("horizontal position error (m)")
    track_ax.set_title("UAV 1, seed 0: error along the flight")
    track_ax.legend(fontsize=7)
    track_ax.grid(alpha=0.3)

    setups = list(dict.fromkeys(r["setup"].split(", ")[0] for r in summary))
    metrics = ("ATE UAV 1 (m)", "RPE (m)", "landmark error (m)")
    x = np.arange(len(setups))
    width = 0.13
    for m, metric in enumerate(metrics):
        for f, fixes in enumerate(("no fixes", "map fixes")):
            values = [
                next((r[metric] for r in summary if r["setup"] == f"{s}, {fixes}"), None) or np.nan
                for s in setups
            ]
            offset = (m * 2 + f - 2.5) * width
            err_ax.bar(
                x + offset,
                values,
                width,
                color=f"C{m + 4}",
                hatch="//" if f == 0 else None,
                edgecolor="white",
                label=f"{metric}, {fixes}",
            )
    err_ax.set_xticks(x, setups)
    err_ax.set_yscale("log")
    err_ax.set_ylabel("median over seeds (m)")
    err_ax.set_title("Trajectory and landmark errors per setup")
    err_ax.legend(fontsize=7, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.08))
    err_ax.grid(alpha=0.3, axis="y", which="both")
    return _save(fig, out)
