"""The speed benchmark's figure: time per stage, what it buys, the companion loop and memory."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.viz.axes import save_figure

_SPEED_STAGES = (
    ("decode_ms", "decode"),
    ("warp_ms", "warp"),
    ("extract_ms", "extract"),
    ("match_ms", "match"),
    ("pose_ms", "pose"),
    ("coarse_ms", "cascade: coarse"),
    ("fine_ms", "cascade: fine (keypoints)"),
    ("verify_ms", "cascade: verification"),
    ("refine_ms", "cascade: refinement"),
    ("other_ms", "other"),
)


def _source_label(row: dict) -> str:
    """' cascade' for a run whose keypoints were the cascade's fine stage, on a line of its own
    with its coarse correlations where the run names them; nothing for keypoints alone."""
    source = row.get("fix_source", "keypoints")
    if source == "keypoints":
        return ""
    backbone = row.get("coarse_backbone")
    return f" {source}" if backbone is None else f"\n{source}: {backbone}"


def _plot_tails(ax: plt.Axes, totals: list[dict], y: np.ndarray) -> np.ndarray:
    """Each run's slow frames: a line from the total's p95 to its max, a dot at p99; returns the
    max (0 where a run has no tails)."""
    p95, p99, worst = (np.array([t.get(k, np.nan) for t in totals]) for k in ("p95", "p99", "max"))
    ax.hlines(y, p95, worst, colors="k", linewidth=1, label="p95 to the slowest frame")
    ax.plot(p99, y, ".", color="k", label="p99")
    return np.nan_to_num(worst)


def _plot_loop_latency(ax: plt.Axes, rows: list[dict], y: np.ndarray) -> None:
    """Each run's companion loop: capture to message at p95 (the bar) and in the median (the
    tick), with the frames whose fixes were fused written at the bar's end."""
    latency = [r.get("latency") or {} for r in rows]
    p95 = np.array([row.get("latency_p95_ms") or 0.0 for row in latency])
    ax.barh(y, p95, color="C4", alpha=0.7)
    ax.plot([row.get("latency_median_ms") or np.nan for row in latency], y, "|", color="k", markersize=18)
    for yi, row, end in zip(y, latency, p95, strict=True):
        if row:
            ax.text(end, yi, f" {row['fused']} of {row['frames']} fused", va="center", fontsize=8)
    ax.set_xlim(0, max(p95.max(), 1.0) * 1.5)
    ax.set_yticks(y, [])
    ax.set_title("Companion loop")
    ax.set_xlabel("capture to message, ms: p95 (bar), | median")
    ax.grid(axis="x", alpha=0.3)


def plot_speed_bench(rows: list[dict], out: Path) -> Path:
    """Per run (backend on engine, alone or as the cascade's fine stage): its mean ms per frame
    split by stage (means add up where medians of stages that only some frames reach do not),
    a tick at the median frame's total and a line from its p95 to the slowest frame (a dot at
    p99), for NAIP same-date and cross-date frames and for real photos, with the accuracy that
    time bought written at the bar's end; beside them the companion loop's latency where the
    runs measured it, and each run's peak memory."""
    panels = [
        ("NAIP same-date, 640 x 480", lambda r: r["naip"]["same-date"], "within_10m", "within 10 m"),
        ("NAIP cross-date, 640 x 480", lambda r: r["naip"]["cross-date"], "within_25m", "within 25 m"),
    ]
    if any(r.get("real") for r in rows):
        panels.append(("real photos, on the DSM", lambda r: r.get("real") or {}, "within_3m", "within 3 m"))
    loop = any(r.get("latency") for r in rows)
    width = 5.2 * len(panels) + 3.8 * (1 + loop)
    fig, axes = plt.subplots(1, len(panels) + 1 + loop, figsize=(width, 0.55 * len(rows) + 2.2))
    labels = [f"{r['features']} ({r['engine']}){_source_label(r)}" for r in rows]
    y = np.arange(len(rows))[::-1]
    for ax, (title, part, key, what) in zip(axes, panels, strict=False):
        left = np.zeros(len(rows))
        for i, (stage, name) in enumerate(_SPEED_STAGES):
            widths = np.array([(part(r).get("mean_ms") or {}).get(stage) or 0.0 for r in rows])
            if widths.any():
                ax.barh(y, widths, left=left, color=f"C{i}", label=name)
                left += widths
        medians = np.array([part(r).get("total_ms") or np.nan for r in rows])
        ax.plot(medians, y, "|", color="k", markersize=18, markeredgewidth=2, label="median frame")
        worst = _plot_tails(ax, [part(r).get("tails_ms", {}).get("total_ms", {}) for r in rows], y)
        ends = np.fmax(np.fmax(left, np.nan_to_num(medians)), worst)
        for yi, r, end in zip(y, rows, ends, strict=True):
            share = part(r).get(key)
            if share is not None:
                ax.text(end, yi, f" {share:.0%} {what}", va="center", fontsize=8)
        ax.set_xlim(0, max(ends.max(), 1.0) * 1.45)
        ax.set_title(title)
        ax.set_xlabel("mean ms a frame by stage; | median, p95 - max (. p99)")
        ax.set_yticks(y, labels)
        ax.grid(axis="x", alpha=0.3)
    if loop:
        _plot_loop_latency(axes[len(panels)], rows, y)
    stages = {}  # stage name -> its bar, over both panels
    for ax in axes[: len(panels)]:
        handles, names = ax.get_legend_handles_labels()
        stages.update(zip(names, handles, strict=True))
    mem_ax = axes[-1]
    mem_ax.barh(y, [r["peak_rss_mb"] for r in rows], color="0.55")
    mem_ax.set_yticks(y, [])  # the rows of the panels beside it, clear of their accuracy text
    mem_ax.set_xlabel("peak resident memory (MB)")
    mem_ax.set_title("Peak memory of the run")
    mem_ax.grid(axis="x", alpha=0.3)
    fig.suptitle("orthonav bench speed: time per stage and what it buys")
    # One legend below the panels, clear of the bars and of the accuracy written at their ends.
    fig.legend(stages.values(), stages.keys(), loc="lower center", ncol=min(len(stages), 5), fontsize=8)
    legend_rows = math.ceil(len(stages) / 5)
    fig.tight_layout(rect=(0, 0.05 + 0.06 * legend_rows, 1, 1))
    return save_figure(fig, out)
