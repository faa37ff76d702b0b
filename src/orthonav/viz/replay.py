"""The replay picture: the logged track and the localizer's fixes over the map, and each fix's
distance from the log over time. Only drawing: every number comes from the replay records."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.mapdb import MapPackage
from orthonav.viz.axes import frame_map, legend_below, log_floor, log_metres_axis, save_figure, to_px


def plot_replay(package: MapPackage, records: list[dict], out: Path, title: str) -> Path:
    """Left, zoomed to the flight: logged track, fixes joined to the logged position they
    estimate, frames not localized. Right: error of each fix (m) against time since the first frame."""
    image, grid = package.preview()
    fig, (ax, err_ax) = plt.subplots(1, 2, figsize=(15, 7), gridspec_kw={"width_ratios": [1.3, 1]})
    ax.imshow(image)
    lc, lr = to_px(grid, [r["log_lat"] for r in records], [r["log_lon"] for r in records])
    ax.plot(lc, lr, "-", color="#00e5ff", lw=2, label="logged track (GNSS)")
    fixed = [i for i, r in enumerate(records) if r["error_m"] is not None]
    if fixed:
        fc, fr = to_px(
            grid, [records[i]["fix"]["lat"] for i in fixed], [records[i]["fix"]["lon"] for i in fixed]
        )
        ax.plot(np.vstack([lc[fixed], fc]), np.vstack([lr[fixed], fr]), "-", color="white", lw=0.8)
        ax.plot(fc, fr, "o", color="#ff4081", ms=5, mec="black", lw=0, label=f"fix ({len(fixed)})")
    missed = [i for i, r in enumerate(records) if r["error_m"] is None]
    if missed:
        ax.plot(
            lc[missed], lr[missed], "x", color="#ffd600", ms=8, mew=2, lw=0, label=f"no fix ({len(missed)})"
        )
    frame_map(ax, image.shape, grid, (lc[0], lr[0]), "the first frame")
    ax.set_title(title)
    _errors(err_ax, records)
    return save_figure(fig, out)


def _errors(ax: plt.Axes, records: list[dict]) -> None:
    t0 = records[0]["time_s"]
    fixed = [r for r in records if r["error_m"] is not None]
    ax.plot([r["time_s"] - t0 for r in fixed], [r["error_m"] for r in fixed], "o-", color="#ff4081", ms=4)
    if fixed:
        median = float(np.median([r["error_m"] for r in fixed]))
        ax.axhline(median, color="grey", ls="--", lw=1, label=f"median {median:.1f} m")
        ax.legend(fontsize=8)
    else:
        ax.text(0.5, 0.5, "no frame fixed", transform=ax.transAxes, ha="center", color="grey")
    ax.set_xlim(0.0, max(records[-1]["time_s"] - t0, 1.0) * 1.05)
    ax.set_xlabel("time since the first frame (s)")
    ax.set_ylabel("fix distance from the logged position (m)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)


def plot_companion_replay(
    nav: list[dict], sent: list[dict], reference: list[dict], fixes: list[dict], out: Path, title: str
) -> Path:
    """A re-run companion log. Left: the tracks in metres (sent, re-run, the autopilot's GNSS where
    the log has it, fixes fused and gated out). Right: the re-run's 1-sigma over time, and the
    re-run's and the sent states' distance from the GNSS."""
    from orthonav.geo import LocalFrame

    frame = LocalFrame(nav[0]["lat"], nav[0]["lon"])

    def enu(records: list[dict]) -> tuple[np.ndarray, np.ndarray]:
        east, north = frame.to_enu([r["lat"] for r in records], [r["lon"] for r in records])
        return np.atleast_1d(east), np.atleast_1d(north)

    fig, (ax, err_ax) = plt.subplots(1, 2, figsize=(15, 7), gridspec_kw={"width_ratios": [1.1, 1]})
    if reference:
        ax.plot(*enu(reference), "-", color="#2e7d32", lw=2, label="autopilot GNSS")
    ax.plot(*enu(nav), "-", color="#1565c0", lw=1.5, label="re-run (1 Hz)")
    if sent:
        ax.plot(*enu(sent), ".", color="#ff6f00", ms=3, label=f"sent ({len(sent)})")
    for fused, marker, colour, name in (
        (True, "o", "#d81b60", "fix fused"),
        (False, "x", "#616161", "fix gated out"),
    ):
        chosen = [f for f in fixes if f["localized"] and f["fused"] == fused]
        if chosen:
            ax.plot(*enu(chosen), marker, color=colour, ms=5, lw=0, label=f"{name} ({len(chosen)})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.grid(alpha=0.3)
    legend_below(ax, ncol=3)
    ax.set_title(title)
    _companion_errors(err_ax, nav, sent)
    return save_figure(fig, out)


def _companion_errors(ax: plt.Axes, nav: list[dict], sent: list[dict]) -> None:
    t0 = nav[0]["time_s"]
    t = [r["time_s"] - t0 for r in nav]
    sigma = [np.nan if r["sigma_m"] is None else r["sigma_m"] for r in nav]
    ax.plot(t, sigma, "--", color="#1565c0", lw=1, label="re-run 1-sigma")
    errors = [(r["time_s"] - t0, r["gnss_error_m"]) for r in nav if r["gnss_error_m"] is not None]
    if errors:
        ax.plot(*zip(*errors, strict=True), "-", color="#1565c0", lw=1.5, label="re-run error vs GNSS")
    sent_errors = [(s["time_s"] - t0, s["gnss_error_m"]) for s in sent if s.get("gnss_error_m") is not None]
    if sent_errors:
        ax.plot(*zip(*sent_errors, strict=True), ".", color="#ff6f00", ms=3, label="sent error vs GNSS")
    log_metres_axis(ax, log_floor(sigma + [e for _, e in errors + sent_errors]))
    ax.set_xlabel("time since the first state (s)")
    ax.set_ylabel("metres")
    legend_below(ax, ncol=3)
