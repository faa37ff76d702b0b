"""Pictures of the SLAM benchmark: trajectories of one seed and the error medians per setup."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.viz.axes import save_figure


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
    return save_figure(fig, out)


def plot_slam_run(
    estimates: list[np.ndarray], truths: list[np.ndarray], landmarks_en: np.ndarray, title: str, out: Path
) -> Path:
    """Left: every UAV's estimated and true track over the landmarks (east/north m); right: each
    UAV's horizontal position error along the flight."""
    fig, (map_ax, err_ax) = plt.subplots(1, 2, figsize=(13, 5.5), gridspec_kw={"width_ratios": [1.1, 1]})
    if len(landmarks_en):
        map_ax.scatter(landmarks_en[:, 0], landmarks_en[:, 1], s=1, color="0.7", label="landmarks")
    for u, (est, true) in enumerate(zip(estimates, truths, strict=True)):
        map_ax.plot(true[:, 0], true[:, 1], "-", color=f"C{u}", lw=2, alpha=0.4, label=f"UAV {u + 1} truth")
        map_ax.plot(est[:, 0], est[:, 1], ".--", color=f"C{u}", lw=1, label=f"UAV {u + 1} estimate")
        err_ax.plot(
            np.linalg.norm(est[:, :2] - true[:, :2], axis=1), "-o", color=f"C{u}", ms=3, label=f"UAV {u + 1}"
        )
    map_ax.set_aspect("equal")
    map_ax.set_xlabel("east (m)")
    map_ax.set_ylabel("north (m)")
    map_ax.legend(fontsize=7)
    map_ax.set_title(title)
    err_ax.set_xlabel("keyframe")
    err_ax.set_ylabel("horizontal position error (m)")
    err_ax.grid(alpha=0.3)
    err_ax.legend(fontsize=8)
    return save_figure(fig, out)
