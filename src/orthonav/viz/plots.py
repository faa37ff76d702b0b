"""PNG plots. Only drawing here: every number plotted was computed elsewhere."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from orthonav.atomic import atomic_path
from orthonav.camera import Camera
from orthonav.geo import GeoGrid
from orthonav.mapdb import MapPackage
from orthonav.types import Fix


def _to_px(grid: GeoGrid, lat: Sequence[float], lon: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    col, row = grid.latlon_to_pixel(np.asarray(lat, float), np.asarray(lon, float))
    return np.atleast_1d(col), np.atleast_1d(row)


def _save(fig: plt.Figure, out: Path) -> Path:
    """Write atomically, so a reader never sees half a PNG."""
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out


def plot_mission(
    package: MapPackage,
    steps: list[dict],
    nav: list[dict],
    start: tuple[float, float],
    target: tuple[float, float],
    out: Path,
) -> Path:
    """ "Drone Trajectory on GeoTIFF Map" beside the navigation error over time.

    Left: true track, the filter's track, the INS alone, fused fixes, fixes the filter gated
    out and frames the localizer rejected. Right: the filter's error with its 3-sigma, the
    INS's error, and each fix's error: the filter is honest when its error stays under 3-sigma.
    """
    image, grid = package.preview()
    fig, (ax, err_ax) = plt.subplots(
        1, 2, figsize=(16, 8), gridspec_kw={"width_ratios": [image.shape[1] / image.shape[0] * 1.1, 1]}
    )
    _mission_map(ax, image, grid, steps, nav, start, target)
    _mission_errors(err_ax, steps, nav)
    return _save(fig, out)


def _mission_map(ax, image, grid, steps, nav, start, target) -> None:
    ax.imshow(image)
    track = nav or steps
    for prefix, style, colour, label in (
        ("true", "-", "#00e5ff", "true track"),
        ("nav", "-", "#ff4081", "navigation filter"),
        ("ins", ":", "#ffab40", "INS alone"),
    ):
        if track and f"{prefix}_lat" in track[0]:
            c, r = _to_px(grid, [s[f"{prefix}_lat"] for s in track], [s[f"{prefix}_lon"] for s in track])
            ax.plot(c, r, style, color=colour, lw=2, label=label)
    for selected, marker, colour, label in (
        ([s for s in steps if s.get("fused", s["accepted"])], "o", "#ff4081", "fused fix"),
        ([s for s in steps if s["accepted"] and not s.get("fused", True)], "D", "#d500f9", "fix gated out"),
    ):
        if selected:
            c, r = _to_px(grid, [s["est_lat"] for s in selected], [s["est_lon"] for s in selected])
            ax.plot(c, r, marker, color=colour, ms=5, mec="black", lw=0, label=f"{label} ({len(selected)})")
    rejected = [s for s in steps if not s["accepted"]]
    if rejected:
        rc, rr = _to_px(grid, [s["true_lat"] for s in rejected], [s["true_lon"] for s in rejected])
        ax.plot(
            rc, rr, "x", color="#ffd600", ms=8, mew=2, lw=0, label=f"frame not localized ({len(rejected)})"
        )
    end = track[-1] if track else {"true_lat": start[0], "true_lon": start[1]}
    for (lat, lon), marker, colour, label in (
        (start, "^", "#76ff03", "start"),
        ((end["true_lat"], end["true_lon"]), "s", "#ffffff", "end (true)"),
        (target, "*", "#ff1744", "target"),
    ):
        c, r = _to_px(grid, [lat], [lon])
        ax.plot(c, r, marker, color=colour, ms=14, mec="black", label=label)
    ax.set_title("Drone Trajectory on GeoTIFF Map")
    ax.set_xlim(0, image.shape[1])
    ax.set_ylim(image.shape[0], 0)
    ax.set_axis_off()
    ax.legend(loc="lower right", fontsize=8, framealpha=0.8)


def _mission_errors(ax, steps: list[dict], nav: list[dict]) -> None:
    if nav:
        t = np.array([r["time_s"] for r in nav])
        ax.plot(t, [r["nav_error_m"] for r in nav], color="#c2185b", lw=2, label="filter error")
        ax.fill_between(
            t, 0, [3 * r["nav_sigma_m"] for r in nav], color="#c2185b", alpha=0.15, label="filter 3-sigma"
        )
        ax.plot(t, [r["ins_error_m"] for r in nav], ":", color="#ef6c00", lw=2, label="INS alone")
    fixed = [s for s in steps if s["error_m"] is not None]
    if fixed:
        ax.plot(
            [s["time_s"] for s in fixed],
            [s["error_m"] for s in fixed],
            "o",
            color="#1565c0",
            ms=4,
            label="fix error",
        )
    ax.set_yscale("symlog", linthresh=10.0)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("horizontal error (m)")
    ax.grid(alpha=0.3)
    ax.set_title("Navigation error")
    ax.legend(fontsize=8)


def plot_fixes(package: MapPackage, fixes: list[tuple[str, Fix]], camera: Camera, out: Path) -> Path:
    """Localized frames over the map: footprint and the point under the drone for each fix."""
    image, grid = package.preview()
    fig, ax = plt.subplots(figsize=(9, 9 * image.shape[0] / image.shape[1]))
    ax.imshow(image)
    accepted = [(name, fix) for name, fix in fixes if fix.accepted]
    for name, fix in accepted:
        corners = fix.pose.footprint_latlon(camera)
        c, r = _to_px(grid, corners[:, 0], corners[:, 1])
        ax.fill(c, r, facecolor="#ff4081", alpha=0.15, edgecolor="#ff4081", lw=1.5)
        dc, dr = _to_px(grid, [fix.pose.lat], [fix.pose.lon])
        ax.plot(dc, dr, "o", color="#00e5ff", ms=5, mec="black")
        ax.annotate(
            name, (dc[0], dr[0]), fontsize=7, color="white", xytext=(4, 4), textcoords="offset points"
        )
    ax.set_title(f"orthonav localize: {len(accepted)} of {len(fixes)} frames fixed")
    ax.set_xlim(0, image.shape[1])
    ax.set_ylim(image.shape[0], 0)
    ax.set_axis_off()
    return _save(fig, out)


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
    return _save(fig, out)


def plot_mission_bench(rows: list[dict], out: Path) -> Path:
    """Arrival (by estimate and by truth) and fix rate per backend, and each mission's error."""
    backends = list(dict.fromkeys(r["features"] for r in rows))
    fig, (rate_ax, err_ax) = plt.subplots(1, 2, figsize=(13, 4.8))
    width = 0.27
    x = np.arange(len(backends))
    for k, (key, label) in enumerate(
        (
            ("arrived", "arrived (by estimate)"),
            ("arrived_true", "arrived (true distance)"),
            ("fix_rate", "fix rate"),
        )
    ):
        shares = [np.mean([float(r[key]) for r in rows if r["features"] == b]) for b in backends]
        rate_ax.bar(x + (k - 1) * width, shares, width, label=label)
    rate_ax.set_xticks(x, backends)
    rate_ax.set_ylim(0, 1.05)
    rate_ax.set_ylabel("share of missions / frames")
    rate_ax.legend(fontsize=8)
    rate_ax.set_title(f"{len(rows) // max(len(backends), 1)} missions per backend, GNSS lost from the start")
    for i, backend in enumerate(backends):
        group = [r for r in rows if r["features"] == backend and r["nav_error_mean_m"] is not None]
        jitter = np.linspace(-0.15, 0.15, len(group)) if len(group) > 1 else np.zeros(len(group))
        err_ax.plot(i + jitter, [r["nav_error_mean_m"] for r in group], "o", color=f"C{i}", ms=4, alpha=0.7)
        err_ax.plot(i + jitter, [r["nav_error_max_m"] for r in group], "^", color=f"C{i}", ms=4, alpha=0.5)
    err_ax.set_xticks(x, backends)
    err_ax.set_yscale("log")
    err_ax.set_ylabel("navigation error per mission (m): o mean, ^ max")
    err_ax.grid(alpha=0.3, which="both")
    err_ax.set_title("Navigation filter error (truth vs estimate, 1 Hz)")
    return _save(fig, out)


def plot_relocalize_bench(rows: list[dict], recall_at: Sequence[int], out: Path) -> Path:
    """Recall of each global index method, lost frames fixed and time per lost frame by fix source
    (keypoints on the index's tiles or on every tile, dense correlation on the index's tiles)."""
    fig, (recall_ax, copy_ax, fixed_ax, time_ax) = plt.subplots(1, 4, figsize=(24, 4.8))
    k = max(recall_at)
    methods = list(dict.fromkeys(r.get("index", "vlad") for r in rows))
    sources = (("index", "o", "keypoints"), ("all tiles", "s", "keypoints, every tile"))
    sources += (("correlation", "^", "correlation"),)
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
    return _save(fig, out)


def plot_mapbuild_bench(rows: list[dict], out: Path) -> Path:
    """Build throughput and peak memory against map size, one line per worker setting."""
    fig, (rate_ax, mem_ax) = plt.subplots(1, 2, figsize=(13, 4.8))
    for i, workers in enumerate(dict.fromkeys(r["workers"] for r in rows)):
        group = [r for r in rows if r["workers"] == workers]
        label = "single process" if workers == "single" else f"Dask, {workers} worker(s)"
        km2 = [r["km2"] for r in group]
        rate_ax.plot(km2, [r["km2_per_min"] for r in group], "o-", color=f"C{i}", label=label)
        mem_ax.plot(km2, [r["peak_mb"] for r in group], "o-", color=f"C{i}", label=label)
    rate_ax.set_ylabel("km^2 per minute (5 m/px imagery)")
    rate_ax.set_title("Map build throughput (ORB)")
    mem_ax.set_ylabel("peak resident memory (MB)")
    mem_ax.set_title("Peak memory of the build")
    for ax in (rate_ax, mem_ax):
        ax.set_xlabel("map area (km^2)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return _save(fig, out)
