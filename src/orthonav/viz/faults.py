"""The fault-injection benchmark at a glance: one panel per scenario, error and 3 sigma over time."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import Patch

from orthonav.viz.axes import log_floor, log_metres_axis, save_figure

UNGRADED_AT_M = 50.0


def plot_fault_bench(
    rows: list[dict],
    fault_at_s: float,
    fault_s: float,
    resume_within_s: float,
    out: Path,
    machine: str = "",
) -> Path:
    """Each scenario's positions as the vehicle graded them: error (dots, red when wrong), the
    3 sigma they claimed (line), the fault (grey) and the time allowed to recover (hatched);
    ``machine`` (how busy it was) goes in the title, beside the recovery it slows."""
    cols = min(4, len(rows))
    nrows = math.ceil(len(rows) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(3.6 * cols, 2.6 * nrows), sharex=True, squeeze=False)
    for ax, row in zip(axes.flat, rows, strict=False):
        _scenario_panel(ax, row, fault_at_s, fault_s, resume_within_s)
    for ax in list(axes.flat)[len(rows) :]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("time since the flight started (s)")
    passed = sum(r["passed"] for r in rows)
    title = f"fault injection: {passed} of {len(rows)} scenarios with no wrong position and recovery"
    fig.suptitle(f"{title} ({machine})" if machine else title)
    handles = {label: h for ax in axes.flat for h, label in zip(*ax.get_legend_handles_labels(), strict=True)}
    handles["fault"] = Patch(color="0.85")
    handles[f"{resume_within_s:.0f} s to recover"] = Patch(facecolor="none", edgecolor="0.8", hatch="//")
    fig.legend(handles.values(), handles.keys(), loc="lower center", ncol=len(handles), fontsize=8)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    return save_figure(fig, out)


def _scenario_panel(ax, row: dict, fault_at_s: float, fault_s: float, resume_within_s: float) -> None:
    end = fault_at_s + fault_s
    ax.axvspan(fault_at_s, end, color="0.85", lw=0)
    ax.axvspan(end, end + resume_within_s, facecolor="none", edgecolor="0.8", hatch="//", lw=0)
    track = sorted(row["track"], key=lambda p: p[0])
    ax.plot(*_broken_at_gaps(track), "-", color="tab:blue", lw=1, label="3 sigma claimed")
    good = [(t, e) for t, e, _, wrong in track if not wrong]
    # A position with no error (its time outside the true track) is drawn at the 50 m line.
    bad = [(t, e if e is not None else UNGRADED_AT_M) for t, e, _, wrong in track if wrong]
    if good:
        ax.plot(*zip(*good, strict=True), ".", color="tab:green", ms=3, label="error (right)")
    if bad:
        ax.plot(*zip(*bad, strict=True), "x", color="tab:red", ms=5, label="error (wrong)")
    log_metres_axis(ax, log_floor([v for _, e, s, _ in track for v in (e, s)]))
    verdict = "pass" if row["passed"] else "FAIL"
    resumed = "-" if row["resumed_s"] is None else f"{row['resumed_s']:.1f} s"
    ax.set_title(
        f"{row['scenario']}: {verdict}\n{row['wrong']} wrong, back in {resumed}",
        fontsize=9,
        color="black" if row["passed"] else "tab:red",
    )
    ax.grid(alpha=0.3, which="both")


def _broken_at_gaps(track: list[list], gap_s: float = 1.0) -> tuple[list[float], list[float]]:
    """(times, 3 sigma) with a break wherever nothing was sent for ``gap_s``: no line across
    a silence, which would claim positions that were never sent."""
    times: list[float] = []
    sigmas: list[float] = []
    for t, _, sigma, _ in track:
        if times and t - times[-1] > gap_s:
            times.append(math.nan)
            sigmas.append(math.nan)
        times.append(t)
        sigmas.append(sigma)
    return times, sigmas
