"""Missions: one mission's picture (its tracks over the map beside its errors over time) and the
mission benchmark's."""

from __future__ import annotations

import textwrap
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import patheffects
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle

from orthonav.geo import GeoGrid
from orthonav.mapdb import MapPackage
from orthonav.viz.axes import OUTLINE, frame_map, legend_below, log_floor, log_metres_axis, save_figure, to_px

TITLE_WRAP = 72  # characters per line of a map's title
ERRORS_TITLE_WRAP = 60  # and of the error plot's, a narrower panel
SIGMA_BAND, SIGMA_LINE, BEYOND_SIGMA = "#b0bec5", "#37474f", "#d50000"  # the filter's bound, its excess
FILTER_ERROR, INS_ERROR = "#c2185b", "#ef6c00"  # the error plot's lines, named at their ends too
END_LABEL = {"textcoords": "offset points", "fontsize": 9, "fontweight": "bold"}  # a line's name at its end

# prefix, line style, colour, width, z-order, label: the truth drawn last, dashed, over the filter;
# thin, so that tracks metres apart stay three lines and not one stripe; the INS a little wider, so
# that its drift reads from afar.
TRACKS = (
    ("ins", ":", "#ffab40", 2.0, 2, "INS alone"),
    ("nav", "-", "#ff4081", 1.5, 3, "navigation filter"),
    ("true", "--", "#00e5ff", 1.2, 4, "true track"),
)


def plot_mission(
    package: MapPackage,
    steps: list[dict],
    nav: list[dict],
    start: tuple[float, float],
    target: tuple[float, float],
    out: Path,
    arrival_radius_m: float | None = None,
    outcome: str = "",
    consistency: str = "",
) -> Path:
    """ "Drone Trajectory on GeoTIFF Map" beside the navigation error over time (see
    :func:`mission_figure`)."""
    figure = mission_figure(package, steps, nav, start, target, arrival_radius_m, outcome, consistency)
    return save_figure(figure, out)


def mission_figure(
    package: MapPackage,
    steps: list[dict],
    nav: list[dict],
    start: tuple[float, float],
    target: tuple[float, float],
    arrival_radius_m: float | None = None,
    outcome: str = "",
    consistency: str = "",
) -> Figure:
    """The mission picture, not yet saved.

    Left, zoomed to the flight: true track, the filter's track, the INS alone, fused fixes,
    fixes the filter gated out, frames the localizer rejected, the target with its arrival
    radius and where the run ended by truth and by estimate; each estimate's legend entry and the
    INS's end say how far from the truth it ended, since at the map's scale a filter metres from
    the truth is drawn on it. Right: the filter's error with its 3-sigma, the INS's error, each
    named at its end with its last value, and each fix's error: the filter is honest when its
    error stays under 3-sigma, and where it does not the excess is filled red. ``outcome`` (one
    line) goes under the map's title, ``consistency`` (how often the error left its sigma
    bounds, the filter's NEES) under the error plot's.
    """
    image, grid = package.preview()
    fig, (ax, err_ax) = plt.subplots(1, 2, figsize=(16, 8))
    _mission_map(ax, image, grid, steps, nav, start, target, arrival_radius_m)
    start_px = to_px(grid, [start[0]], [start[1]])
    frame_map(ax, image.shape, grid, (start_px[0][0], start_px[1][0]), "the start zone centre")
    ax.set_title("\n".join(["Drone trajectory on the map", *textwrap.wrap(outcome, TITLE_WRAP)]))
    _mission_errors(err_ax, steps, nav, consistency)
    (left, right), (bottom, top) = ax.get_xlim(), ax.get_ylim()
    ax.get_gridspec().set_width_ratios([(right - left) / (bottom - top), 1.0])
    return fig


def _mission_map(
    ax: Axes,
    image: np.ndarray,
    grid: GeoGrid,
    steps: list[dict],
    nav: list[dict],
    start: tuple[float, float],
    target: tuple[float, float],
    arrival_radius_m: float | None,
) -> None:
    ax.imshow(image)
    track = nav or steps
    _mission_tracks(ax, grid, track)
    _mission_frames(ax, grid, steps)
    if arrival_radius_m:
        c, r = to_px(grid, [target[0]], [target[1]])
        circle = Circle((c[0], r[0]), arrival_radius_m / grid.gsd_m, fill=False, ls="--", lw=1.5)
        circle.set(edgecolor="#ff1744", zorder=3, label=f"arrival radius ({arrival_radius_m:g} m)")
        ax.add_patch(circle)
    for (lat, lon), marker, colour, label in _mission_places(track, start, target):
        c, r = to_px(grid, [lat], [lon])
        ax.plot(c, r, marker, color=colour, ms=13, mec="black", zorder=6, label=label)


def _mission_tracks(ax: Axes, grid: GeoGrid, track: list[dict]) -> None:
    """The true track and each estimate's, the estimates' labels saying how far from the truth
    they ended, and the INS's end named on the map where it drifted to."""
    ends = _end_offsets(track)
    for prefix, style, colour, width, zorder, label in TRACKS:
        if not track or f"{prefix}_lat" not in track[0]:
            continue
        c, r = to_px(grid, [s[f"{prefix}_lat"] for s in track], [s[f"{prefix}_lon"] for s in track])
        if prefix in ends:
            label = f"{label} ({_short_m(ends[prefix])} from the truth at the end)"
        stroke = [patheffects.withStroke(linewidth=width + 0.8, foreground="black")]
        ax.plot(c, r, style, color=colour, lw=width, zorder=zorder, label=label, path_effects=stroke)
        if prefix == "ins" and "ins" in ends:
            truth = to_px(grid, [track[-1]["true_lat"]], [track[-1]["true_lon"]])
            text = f"INS alone: {_short_m(ends['ins'])} off"
            _name_end(ax, text, (c, r), (truth[0][0], truth[1][0]), colour)


def _end_offsets(track: list[dict]) -> dict[str, float]:
    """How far each estimate (by track prefix) ended from the truth, where the track says."""
    last = track[-1] if track else {}
    errors = {"nav": last.get("nav_error_m"), "ins": last.get("ins_error_m")}
    return {prefix: float(error) for prefix, error in errors.items() if error is not None}


def _short_m(metres: float) -> str:
    return f"{metres:.0f} m" if metres >= 10 else f"{metres:.1f} m"


def _name_end(
    ax: Axes, text: str, track: tuple[np.ndarray, np.ndarray], truth: tuple[float, float], colour: str
) -> None:
    """``text`` at a track's end (map pixels): above or below it, away from the true end, and
    reaching back the way the track came, where the view has room (the end may be at its edge)."""
    end = (track[0][-1], track[1][-1])
    back, south = track[0][0] - end[0], end[1] - truth[1]
    ha, va = "right" if back < 0 else "left", "top" if south > 0 else "bottom"
    offset = (0, -8 if south > 0 else 8)
    ax.annotate(text, end, offset, ha=ha, va=va, color=colour, path_effects=OUTLINE, zorder=7, **END_LABEL)


def _mission_frames(ax: Axes, grid: GeoGrid, steps: list[dict]) -> None:
    """Fixes fused (at the estimate), gated out (at the estimate), frames not localized (at the truth)."""
    for selected, marker, colour, label in (
        ([s for s in steps if s.get("fused", s["accepted"])], "o", "#ff4081", "fused fix"),
        ([s for s in steps if s["accepted"] and not s.get("fused", True)], "D", "#d500f9", "fix gated out"),
    ):
        if selected:
            c, r = to_px(grid, [s["est_lat"] for s in selected], [s["est_lon"] for s in selected])
            ax.plot(
                c,
                r,
                marker,
                color=colour,
                ms=5,
                mec="black",
                lw=0,
                zorder=5,
                label=f"{label} ({len(selected)})",
            )
    rejected = [s for s in steps if not s["accepted"]]
    if rejected:
        rc, rr = to_px(grid, [s["true_lat"] for s in rejected], [s["true_lon"] for s in rejected])
        ax.plot(
            rc,
            rr,
            "x",
            color="#ffd600",
            ms=8,
            mew=2,
            lw=0,
            zorder=5,
            label=f"frame not localized ({len(rejected)})",
        )


def _mission_places(
    track: list[dict], start: tuple[float, float], target: tuple[float, float]
) -> list[tuple[tuple[float, float], str, str, str]]:
    """The start, where the run ended (by truth and by estimate) and the target."""
    places = [(start, "^", "#76ff03", "start zone centre")]
    if track:
        last = track[-1]
        places.append(((last["true_lat"], last["true_lon"]), "s", "#ffffff", "end (true)"))
        if "nav_lat" in last:
            places.append(((last["nav_lat"], last["nav_lon"]), "P", "#ff4081", "end (estimate)"))
    places.append((target, "*", "#ff1744", "target"))
    return places


def _mission_errors(ax: Axes, steps: list[dict], nav: list[dict], consistency: str = "") -> None:
    fixed = [s for s in steps if s["error_m"] is not None]
    sigma3 = np.array([3 * r["nav_sigma_m"] for r in nav], float)
    floor = log_floor([s["error_m"] for s in fixed] + [r["nav_error_m"] for r in nav] + list(sigma3))
    if nav:
        t = np.array([r["time_s"] for r in nav])
        error = np.array([r["nav_error_m"] for r in nav], float)
        # The bound in a colour of its own, and the error above it filled red: a filter leaving
        # its 3-sigma must show as such, not vanish in a band of its own colour.
        ax.fill_between(t, floor, sigma3, color=SIGMA_BAND, alpha=0.35, lw=0)
        ax.plot(t, sigma3, "--", color=SIGMA_LINE, lw=1.2, label="filter 3-sigma")
        above = error > sigma3
        if above.any():
            beyond = {"color": BEYOND_SIGMA, "alpha": 0.45, "lw": 0, "label": "error above 3-sigma"}
            ax.fill_between(t, sigma3, error, where=above, interpolate=True, **beyond)
        ins = np.array([r["ins_error_m"] for r in nav], float)
        ax.plot(t, error, color=FILTER_ERROR, lw=2, label="filter error")
        ax.plot(t, ins, ":", color=INS_ERROR, lw=2, label="INS alone")
        _name_line_ends(ax, t[-1], (("filter", error[-1], FILTER_ERROR), ("INS alone", ins[-1], INS_ERROR)))
    if fixed:
        times, errors = [s["time_s"] for s in fixed], [s["error_m"] for s in fixed]
        ax.plot(times, errors, "o", color="#1565c0", ms=4, label="fix error")
    if not nav and not fixed:
        ax.text(0.5, 0.5, "nothing flown", transform=ax.transAxes, ha="center", color="grey")
    log_metres_axis(ax, floor)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("horizontal error (m)")
    ax.set_title("\n".join(["Navigation error", *textwrap.wrap(consistency, ERRORS_TITLE_WRAP)]))
    legend_below(ax, ncol=2)


def _name_line_ends(ax: Axes, t_end: float, lines: tuple[tuple[str, float, str], ...]) -> None:
    """Each line's name and last value over its right end: the reader need not match colours to
    the legend to see which error is which, nor read the axis to see how far the INS drifted."""
    for name, value, colour in lines:
        ax.annotate(
            f"{name}: {_short_m(value)}",
            (t_end, value),
            (0, 4),
            ha="right",
            va="bottom",
            color=colour,
            **END_LABEL,
        )


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
    legend_below(rate_ax, 3)
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
    return save_figure(fig, out)
