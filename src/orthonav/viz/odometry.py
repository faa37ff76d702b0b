"""Plots of visual odometry and key-object benchmarks. Only drawing: numbers come from elsewhere."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from orthonav.viz.axes import save_figure


def plot_vo_track(tracks: dict[str, tuple[list[float], list[float]]], out: Path, title: str = "") -> Path:
    """Tracks (east/x, north/y in metres) drawn together, the first one as the reference."""
    fig, ax = plt.subplots(figsize=(7, 6))
    for i, (name, (x, y)) in enumerate(tracks.items()):
        ax.plot(x, y, "-o" if i else "-s", ms=3, lw=2 if i == 0 else 1.2, label=name)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(title)
    return save_figure(fig, out)


def plot_odometry_bench(rows: list[dict], configs: list[str], out: Path) -> Path:
    """Per-pair displacement and heading-change error of each configuration."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for config in configs:
        sel = [r for r in rows if r["config"] == config]
        x = [r["index"] for r in sel]
        axes[0].plot(x, [r.get("displacement_error_m") for r in sel], "o-", ms=3, label=config)
        axes[1].plot(
            x,
            [abs(r.get("dyaw_error_deg") or float("nan")) if r["ok"] else None for r in sel],
            "o-",
            ms=3,
            label=config,
        )
    axes[0].set_ylabel("displacement error vs GNSS (m)")
    axes[1].set_ylabel("|heading-change error| vs gimbal yaw (deg)")
    for ax in axes:
        ax.set_xlabel("photo pair (index of the second photo)")
        ax.set_yscale("symlog", linthresh=1.0)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    return save_figure(fig, out)


def plot_robustness_bench(rows: list[dict], out: Path) -> Path:
    """Repeatability (top) and matching score (bottom) vs change level: one column per condition,
    one line per detector and source."""
    conditions = sorted({r["condition"] for r in rows})
    fig, axes = plt.subplots(2, len(conditions), figsize=(4 * len(conditions), 7.5), squeeze=False)
    for col, condition in enumerate(conditions):
        for row_index, suffix in enumerate(("", "_match")):
            ax = axes[row_index][col]
            for source, style in (("naip", "-"), ("drone", "--")):
                sel = [r for r in rows if r["condition"] == condition and r["source"] == source]
                for name, colour in (("orb", "C0"), ("sift", "C1"), ("lowlevel", "C2"), ("lines", "C3")):
                    if sel:
                        ax.plot(
                            [r["level"] for r in sel],
                            [r[name + suffix] for r in sel],
                            style,
                            color=colour,
                            marker="o",
                            ms=3,
                            label=f"{name} ({source})",
                        )
            ax.set_title(f"{condition}: {'repeatability' if row_index == 0 else 'matching score'}")
            ax.set_ylim(0, 1)
            ax.set_xlabel("level")
            ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("found again (pts 2 px; segs 3 px, 5 deg)")
    axes[1][0].set_ylabel("descriptor match correct")
    axes[0][-1].legend(fontsize=7)
    return save_figure(fig, out)
