"""The SITL benchmark at a glance: per flight, the tracks over the map and the errors over time."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.geo import distance_m
from orthonav.mapdb import MapPackage
from orthonav.viz.axes import frame_map, save_figure, to_px

TARGET_P95_M, TARGET_MAX_M = 10.0, 25.0


def plot_sitl_bench(result: dict, runs: Path, out: Path, machine: str = "") -> Path:
    """One row per flight. Left: SITL's true track, the autopilot's estimate and orthonav's
    positions over the map, home and where GNSS went. Right: the autopilot's and orthonav's
    horizontal errors against the truth, the GNSS-off span shaded, the targets as lines."""
    package = MapPackage(Path(result["map"]))
    image, grid = package.preview()
    rows = result["rows"]
    # Constrained: each map's legend sits under it, clear of the next row's title.
    fig, axes = plt.subplots(len(rows), 2, figsize=(15, 6 * len(rows)), squeeze=False, layout="constrained")
    for (map_ax, err_ax), row in zip(axes, rows, strict=True):
        track = json.loads((runs / row["name"] / "track.json").read_text())
        _tracks_on_map(map_ax, image, grid, row, track)
        _errors(err_ax, row, track)
    fig.suptitle(f"ArduPilot SITL with orthonav: GNSS denied in flight ({machine})" if machine else "")
    return save_figure(fig, out)


def _tracks_on_map(ax, image: np.ndarray, grid, row: dict, track: dict) -> None:
    ax.imshow(image)
    truth = np.asarray(track["truth"], float).reshape(-1, 3)
    estimate = np.asarray(track["estimate"], float).reshape(-1, 4)
    if truth.size:
        ax.plot(*to_px(grid, truth[:, 1], truth[:, 2]), "-", color="white", lw=3, label="truth (SIMSTATE)")
    if estimate.size:
        ax.plot(
            *to_px(grid, estimate[:, 1], estimate[:, 2]),
            "-",
            color="#ff9100",
            lw=1.5,
            label="autopilot's estimate",
        )
    sent = (row.get("orthonav_messages") or {}).get("track") or []
    if sent:
        lat, lon = np.asarray(sent, float)[:, 1], np.asarray(sent, float)[:, 2]
        ax.plot(*to_px(grid, lat, lon), ".", color="#2979ff", ms=2, label="orthonav's positions sent")
    home = track["home"]
    hc, hr = to_px(grid, [home[0]], [home[1]])
    ax.plot(hc, hr, "*", color="yellow", mec="black", ms=16, label="home (planned landing)")
    off_at = track.get("gnss_off_at")
    if off_at is not None and truth.size:
        i = int(np.searchsorted(truth[:, 0], off_at))
        i = min(i, len(truth) - 1)
        c, r = to_px(grid, [truth[i, 1]], [truth[i, 2]])
        ax.plot(c, r, "X", color="red", mec="black", ms=12, label=_denial(row))
    frame_map(ax, image.shape, grid, (hc[0], hr[0]), "home")
    landed = "-" if row["landing_error_m"] is None else f"{row['landing_error_m']:.1f} m"
    verdict = "completed" if row["completed"] else "NOT completed"
    ended = "loitered over home" if row.get("vehicle") == "plane" else "landed"
    ax.set_title(
        f"{row['name']}: {verdict}, {ended} {landed} from plan",
        color="black" if row["completed"] else "tab:red",
    )


def _errors(ax, row: dict, track: dict) -> None:
    start = track.get("armed_at") or (track["truth"][0][0] if track["truth"] else 0.0)
    off_at, ended = track.get("gnss_off_at"), track.get("gnss_back_at") or track.get("ended_at")
    if off_at is not None:
        ax.axvspan(off_at - start, (ended or off_at) - start, color="0.9", lw=0, label=_denial(row))
    if track.get("fault_from") is not None and track.get("fault_to") is not None:
        fault = (track["fault_from"] - start, track["fault_to"] - start)
        ax.axvspan(*fault, color="tab:red", alpha=0.2, lw=0, label=f"fault: {row.get('fault')}")
    estimate = np.asarray(track["estimate"], float).reshape(-1, 4)
    # From arming: before its EKF has an origin an autopilot may report a position near (0, 0).
    estimate = estimate[estimate[:, 0] >= start]
    if estimate.size:
        ax.plot(
            estimate[:, 0] - start, estimate[:, 3], "-", color="#ff9100", lw=1.2, label="autopilot's error"
        )
    sent = (row.get("orthonav_messages") or {}).get("track") or []
    truth = np.asarray(track["truth"], float).reshape(-1, 3)
    if sent and truth.size:
        t, lat, lon = np.asarray(sent, float).T
        true_lat, true_lon = np.interp(t, truth[:, 0], truth[:, 1]), np.interp(t, truth[:, 0], truth[:, 2])
        err = np.asarray(distance_m(true_lat, true_lon, lat, lon), float)
        ax.plot(t - start, err, ".", color="#2979ff", ms=2, label="orthonav's position error")
    for level, label in ((TARGET_P95_M, "p95 target"), (TARGET_MAX_M, "max target")):
        ax.axhline(level, ls="--", lw=0.8, color="0.4")
        ax.annotate(
            label, (0.99, level), xycoords=("axes fraction", "data"), fontsize=7, va="bottom", ha="right"
        )
    ax.set_yscale("symlog", linthresh=10.0)
    ax.set_ylim(bottom=0.0)
    ax.set_xlabel("time since arming (s)")
    ax.set_ylabel("horizontal error against SITL's truth (m)")
    p50, p95, worst = (row[f"horizontal_error_{k}_m"] for k in ("p50", "p95", "max"))
    ax.set_title(f"autopilot's error, {_denial(row)}: p50 {p50} m, p95 {p95} m, max {worst} m")
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="upper left", fontsize=8)


def _denial(row: dict) -> str:
    """What happened to GNSS in this flight: taken away, or moved by a spoofer."""
    return "GNSS spoofed" if row.get("gnss") == "spoofed" else "GNSS off"
