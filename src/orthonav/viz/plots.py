"""PNG plots. Only drawing here: every number plotted was computed elsewhere."""

from __future__ import annotations

import math
import re
import textwrap
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import patheffects
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Circle
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter
from matplotlib.transforms import Bbox, offset_copy
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from orthonav.atomic import atomic_path
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.geo import GeoGrid
from orthonav.mapdb import MapPackage
from orthonav.types import Fix, Prior

ZOOM_MARGIN = 0.12  # of the plotted points' extent, on each side of a zoomed map
MIN_MARGIN = 0.04  # of the map's longer side: a short flight still shows the ground around it
MIN_ASPECT = 0.6  # a zoomed view's shorter side, at least, as a share of its longer side
LEGEND_GAP_PT = 40.0  # legends hang this far below their axes, under the tick labels
OUTLINE = [patheffects.withStroke(linewidth=2.5, foreground="black")]
# Rejected frames: one colour per reason, the rarer reasons together in the last.
REJECTED_COLOURS = ("#ffd600", "#ff9100", "#ff1744", "#e040fb")
# Where a frame's name may go around its point: (dx, dy) in points and the text's alignment.
LABEL_OFFSETS = ((4, 4, "left", "bottom"), (4, -4, "left", "top"), (-4, 4, "right", "bottom"))
LABEL_OFFSETS += ((-4, -4, "right", "top"),)
# The scale bar goes in the corner with the fewest plotted points near it (axes fractions).
CORNERS = {"lower left": (0.0, 0.0), "lower right": (1.0, 0.0), "upper left": (0.0, 1.0)}
CORNERS |= {"upper right": (1.0, 1.0)}
CORNER_REACH = (0.3, 0.15)
NORTH_ARROW = 0.08  # the north arrow's length, in axes fractions
TITLE_WRAP = 72  # characters per line of a map's title
LEGEND_WRAP = 44  # characters per line of a legend entry: wrapped, never cut
NUMBER = re.compile(r"\d+(?:\.\d+)?")
SIGMA_BAND, SIGMA_LINE, BEYOND_SIGMA = "#b0bec5", "#37474f", "#d50000"  # the filter's bound, its excess


def _to_px(grid: GeoGrid, lat: Sequence[float], lon: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    col, row = grid.latlon_to_pixel(np.asarray(lat, float), np.asarray(lon, float))
    return np.atleast_1d(col), np.atleast_1d(row)


def _save(fig: Figure, out: Path) -> Path:
    """Write atomically, so a reader never sees half a PNG. The format is the suffix's (PNG for
    none), named to matplotlib: it would read the temporary's, and append '.png' to a name
    without one (writing beside ``/dev/null``, not to it)."""
    kind = out.suffix.lstrip(".").lower() or "png"
    supported = fig.canvas.get_supported_filetypes()
    if kind not in supported:
        plt.close(fig)
        raise OrthonavError(f"{out}: a plot can be written as {', '.join(sorted(supported))}, not {kind!r}")
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format=kind, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return out


# --- maps: zoomed to what is drawn, in metres, with a scale bar and the legend outside ---------


def view_box(cols: Sequence[float], rows: Sequence[float], shape: tuple[int, ...]) -> tuple[float, ...]:
    """(left, right, bottom, top) in map pixels framing every point with a margin.

    A flight over part of a large map would otherwise be a thin line: the view is the points'
    bounds plus a margin (the map around them as context), widened to a readable aspect and
    cut at the map's edges unless points lie beyond them. Rows grow downwards: bottom > top.
    """
    cols, rows = np.asarray(cols, float).ravel(), np.asarray(rows, float).ravel()
    height, width = shape[:2]
    keep = np.isfinite(cols) & np.isfinite(rows)
    if not keep.any():
        return 0.0, float(width), float(height), 0.0
    cols, rows = cols[keep], rows[keep]
    margin = max(ZOOM_MARGIN * max(np.ptp(cols), np.ptp(rows)), MIN_MARGIN * max(width, height))
    half_w, half_h = np.ptp(cols) / 2.0 + margin, np.ptp(rows) / 2.0 + margin
    half_w, half_h = max(half_w, MIN_ASPECT * half_h), max(half_h, MIN_ASPECT * half_w)
    left, right = _span(cols, half_w, width)
    top, bottom = _span(rows, half_h, height)
    return left, right, bottom, top


def _span(values: np.ndarray, half: float, size: int) -> tuple[float, float]:
    """The values' centre +- half, cut at the map's edges (0, size) where no value lies beyond."""
    centre = (values.min() + values.max()) / 2.0
    low, high = centre - half, centre + half
    if values.min() >= 0.0:
        low = max(low, 0.0)
    if values.max() <= size:
        high = min(high, float(size))
    return float(low), float(high)


def _plotted_points(ax: Axes) -> tuple[np.ndarray, np.ndarray]:
    """Every vertex drawn in data coordinates: lines, markers and patches (e.g. a radius circle)."""
    xy = [line.get_xydata() for line in ax.get_lines()]
    xy += [p.get_patch_transform().transform(p.get_path().vertices) for p in ax.patches]
    points = np.concatenate([np.reshape(a, (-1, 2)) for a in xy]) if xy else np.empty((0, 2))
    return points[:, 0], points[:, 1]


def _frame_map(
    ax: Axes, shape: tuple[int, ...], grid: GeoGrid, origin_px: tuple[float, float], origin: str
) -> None:
    """Zoom to what is drawn, label the axes in metres from ``origin``, add a scale bar and put
    the legend under the map, where it hides nothing."""
    left, right, bottom, top = view_box(*_plotted_points(ax), shape)
    ax.set_xlim(left, right)
    ax.set_ylim(bottom, top)
    _metre_ticks(ax, grid, origin_px, origin)
    bar_corner, arrow_corner = _corners_by_crowd(ax)[:2]
    _scale_bar(ax, grid, bar_corner)
    _north_arrow(ax, grid, arrow_corner)
    _legend_below(ax, ncol=3)


def _metre_ticks(ax: Axes, grid: GeoGrid, origin_px: tuple[float, float], origin: str) -> None:
    """Round metres east and north of ``origin_px``; the data stay map pixels, so everything drawn
    lines up with the image."""
    gx, gy = grid.gsd_xy_m
    ox, oy = origin_px
    (left, right), (bottom, top) = ax.get_xlim(), ax.get_ylim()
    east = _ticks_within((left - ox) * gx, (right - ox) * gx)
    north = _ticks_within((oy - bottom) * gy, (oy - top) * gy)
    ax.set_xticks(ox + east / gx, [_metres(v) for v in east])
    ax.set_yticks(oy - north / gy, [_metres(v) for v in north])
    ax.set_xlim(left, right)
    ax.set_ylim(bottom, top)
    lat, lon = grid.pixel_to_latlon([ox], [oy])
    ax.set_xlabel(f"metres east of {origin} ({_latlon_text(float(lat[0]), float(lon[0]))})")
    ax.set_ylabel(f"metres north of {origin}")


def _latlon_text(lat: float, lon: float) -> str:
    return f"{abs(lat):.5f}° {'N' if lat >= 0 else 'S'}, {abs(lon):.5f}° {'E' if lon >= 0 else 'W'}"


def _ticks_within(low: float, high: float) -> np.ndarray:
    ticks = MaxNLocator(nbins=6, steps=[1, 2, 2.5, 5, 10]).tick_values(low, high)
    return ticks[(ticks >= low) & (ticks <= high)]


def _metres(value: float) -> str:
    value = float(value) + 0.0  # no "-0"
    return f"{value:.0f}" if value.is_integer() else f"{value:g}"


def _scale_bar(ax: Axes, grid: GeoGrid, corner: str) -> None:
    """A bar of a round length, about a fifth of the view, in ``corner``."""
    m_per_px = grid.gsd_xy_m[0]
    (left, right), (bottom, top) = ax.get_xlim(), ax.get_ylim()
    length_m = _round_length((right - left) * m_per_px / 5.0)
    label = f"{length_m / 1000:g} km" if length_m >= 1000 else f"{length_m:g} m"
    bar = AnchoredSizeBar(
        ax.transData,
        length_m / m_per_px,
        label,
        corner,
        pad=0.4,
        borderpad=0.8,
        sep=4,
        size_vertical=abs(bottom - top) / 120.0,
        frameon=True,
    )
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)


def _round_length(at_most: float) -> float:
    """The largest 1, 2 or 5 times a power of ten not above ``at_most``."""
    power = 10.0 ** math.floor(math.log10(at_most))
    return next(s * power for s in (5.0, 2.0, 1.0) if s * power <= at_most)


def _north_arrow(ax: Axes, grid: GeoGrid, corner: str) -> None:
    """An arrow to true north at the view's centre, marked N, in ``corner``: a map in a projected
    CRS need not have north straight up."""
    (left, right), (bottom, top) = ax.get_xlim(), ax.get_ylim()
    col, row = (left + right) / 2.0, (bottom + top) / 2.0
    lat, lon = grid.pixel_to_latlon([col], [row])
    north_col, north_row = _to_px(grid, [float(lat[0]) + 1e-3], [float(lon[0])])
    east, up = north_col[0] - col, row - north_row[0]  # rows grow downwards
    east, up = east / math.hypot(east, up), up / math.hypot(east, up)
    cx, cy = CORNERS[corner]
    base = (0.06 + 0.88 * cx, 0.05 + 0.78 * cy)
    head = (base[0] + NORTH_ARROW * east, base[1] + NORTH_ARROW * up)
    arrow = {"arrowstyle": "-|>", "color": "white", "lw": 2}
    ax.annotate("", head, base, xycoords="axes fraction", arrowprops=arrow, zorder=7)
    ax.annotate(
        "N",
        head,
        xycoords="axes fraction",
        ha="center",
        va="bottom",
        color="white",
        fontsize=11,
        fontweight="bold",
        path_effects=OUTLINE,
        zorder=7,
    )


def _corners_by_crowd(ax: Axes) -> list[str]:
    """The corners of the axes, those with the fewest plotted points near them first."""
    cols, rows = _plotted_points(ax)
    fx, fy = ax.transLimits.transform(np.column_stack([cols, rows])).T if len(cols) else ([], [])
    fx, fy = np.asarray(fx), np.asarray(fy)

    def crowd(corner: str) -> int:
        cx, cy = CORNERS[corner]
        return int(np.sum((np.abs(fx - cx) < CORNER_REACH[0]) & (np.abs(fy - cy) < CORNER_REACH[1])))

    return sorted(CORNERS, key=crowd)


def _legend_below(ax: Axes, ncol: int) -> None:
    """Under the axes, below their tick labels: a legend inside the data hides what it explains."""
    if not ax.get_legend_handles_labels()[0]:
        return
    below = offset_copy(ax.transAxes, fig=ax.figure, y=-LEGEND_GAP_PT, units="points")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, 0.0), bbox_transform=below, ncol=ncol, fontsize=8)


def _log_metres_axis(ax: Axes, floor_m: float) -> None:
    """Log y (errors span decades) from ``floor_m`` up, labelled 1-2-5 in plain metres with minor
    ticks between. Call it once everything is drawn: setting the floor fixes the top too."""
    ax.set_yscale("log")
    ax.autoscale(axis="y")
    ax.set_ylim(bottom=floor_m)
    ax.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 2.0, 5.0), numticks=40))
    ax.yaxis.set_minor_locator(LogLocator(base=10.0, subs=np.arange(1.0, 10.0), numticks=40))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: _metres(v) if v >= 1 else f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())
    ax.grid(which="major", alpha=0.35)
    ax.grid(which="minor", alpha=0.12)


def _log_floor(values: Sequence[float | None]) -> float:
    """The power of ten under the smallest positive value (1 m when there is none)."""
    positive = [v for v in values if v is not None and np.isfinite(v) and v > 0]
    return 10.0 ** math.floor(math.log10(min(positive))) if positive else 1.0


# --- missions ----------------------------------------------------------------------------------

# prefix, line style, colour, width, z-order, label: the truth drawn last, dashed, over the filter;
# thin, so that tracks metres apart stay three lines and not one stripe.
TRACKS = (
    ("ins", ":", "#ffab40", 1.5, 2, "INS alone"),
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
    return _save(figure, out)


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
    radius and where the run ended by truth and by estimate. Right: the filter's error with its
    3-sigma, the INS's error, and each fix's error: the filter is honest when its error stays
    under 3-sigma, and where it does not the excess is filled red. ``outcome`` (one line) goes
    under the map's title, ``consistency`` (how often the error left its sigma bounds, the
    filter's NEES) under the error plot's.
    """
    image, grid = package.preview()
    fig, (ax, err_ax) = plt.subplots(1, 2, figsize=(16, 8))
    _mission_map(ax, image, grid, steps, nav, start, target, arrival_radius_m)
    start_px = _to_px(grid, [start[0]], [start[1]])
    _frame_map(ax, image.shape, grid, (start_px[0][0], start_px[1][0]), "the start zone centre")
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
    for prefix, style, colour, width, zorder, label in TRACKS:
        if track and f"{prefix}_lat" in track[0]:
            c, r = _to_px(grid, [s[f"{prefix}_lat"] for s in track], [s[f"{prefix}_lon"] for s in track])
            stroke = [patheffects.withStroke(linewidth=width + 0.8, foreground="black")]
            ax.plot(c, r, style, color=colour, lw=width, zorder=zorder, label=label, path_effects=stroke)
    _mission_frames(ax, grid, steps)
    if arrival_radius_m:
        c, r = _to_px(grid, [target[0]], [target[1]])
        circle = Circle((c[0], r[0]), arrival_radius_m / grid.gsd_m, fill=False, ls="--", lw=1.5)
        circle.set(edgecolor="#ff1744", zorder=3, label=f"arrival radius ({arrival_radius_m:g} m)")
        ax.add_patch(circle)
    for (lat, lon), marker, colour, label in _mission_places(track, start, target):
        c, r = _to_px(grid, [lat], [lon])
        ax.plot(c, r, marker, color=colour, ms=13, mec="black", zorder=6, label=label)


def _mission_frames(ax: Axes, grid: GeoGrid, steps: list[dict]) -> None:
    """Fixes fused (at the estimate), gated out (at the estimate), frames not localized (at the truth)."""
    for selected, marker, colour, label in (
        ([s for s in steps if s.get("fused", s["accepted"])], "o", "#ff4081", "fused fix"),
        ([s for s in steps if s["accepted"] and not s.get("fused", True)], "D", "#d500f9", "fix gated out"),
    ):
        if selected:
            c, r = _to_px(grid, [s["est_lat"] for s in selected], [s["est_lon"] for s in selected])
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
        rc, rr = _to_px(grid, [s["true_lat"] for s in rejected], [s["true_lon"] for s in rejected])
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
    floor = _log_floor([s["error_m"] for s in fixed] + [r["nav_error_m"] for r in nav] + list(sigma3))
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
        ax.plot(t, error, color="#c2185b", lw=2, label="filter error")
        ax.plot(t, [r["ins_error_m"] for r in nav], ":", color="#ef6c00", lw=2, label="INS alone")
    if fixed:
        times, errors = [s["time_s"] for s in fixed], [s["error_m"] for s in fixed]
        ax.plot(times, errors, "o", color="#1565c0", ms=4, label="fix error")
    if not nav and not fixed:
        ax.text(0.5, 0.5, "nothing flown", transform=ax.transAxes, ha="center", color="grey")
    _log_metres_axis(ax, floor)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("horizontal error (m)")
    ax.set_title("\n".join(["Navigation error", *textwrap.wrap(consistency, TITLE_WRAP)]))
    _legend_below(ax, ncol=2)


# --- localize --plot ---------------------------------------------------------------------------


def plot_fixes(
    package: MapPackage,
    fixes: list[tuple[str, Fix]],
    camera: Camera,
    out: Path,
    priors: Mapping[str, Prior] | None = None,
) -> Path:
    """Localized and rejected frames over the map (see :func:`fixes_figure`)."""
    return _save(fixes_figure(package, fixes, camera, priors), out)


def fixes_figure(
    package: MapPackage,
    fixes: list[tuple[str, Fix]],
    camera: Camera,
    priors: Mapping[str, Prior] | None = None,
) -> Figure:
    """Each fix's footprint outlined thinly and the point under the drone, named where the name
    covers no other name or marker, the least sure fix ringed; each rejected frame an x at its
    prior position (``priors`` by frame name), one colour per reason, its numbers as the range
    they span. The view is zoomed to what is drawn."""
    image, grid = package.preview()
    fig, ax = plt.subplots(figsize=(10, 10))
    ax.imshow(image)
    accepted = [(name, fix) for name, fix in fixes if fix.accepted]
    points = _draw_fixes(ax, grid, accepted, camera)
    rejected = [(name, fix) for name, fix in fixes if not fix.accepted]
    unplaced = _draw_rejected(ax, grid, rejected, priors or {})
    centre = (image.shape[1] / 2.0, image.shape[0] / 2.0)
    _frame_map(ax, image.shape, grid, centre, "the map centre")
    title = f"orthonav localize: {len(accepted)} of {len(fixes)} frames fixed"
    if unplaced:
        title += f"\n{unplaced} rejected frame(s) without a prior position, not drawn"
    ax.set_title(title)
    _label_points(ax, points)
    return fig


def _draw_fixes(
    ax: Axes, grid: GeoGrid, accepted: list[tuple[str, Fix]], camera: Camera
) -> list[tuple[str, float, float]]:
    """Footprints as outlines (filled, overlapping ones merge into a blob) and the points under
    the drone; returns (name, col, row) of each point."""
    points = []
    for i, (name, fix) in enumerate(accepted):
        corners = fix.pose.footprint_latlon(camera)
        c, r = _to_px(grid, corners[:, 0], corners[:, 1])
        label = "camera footprint" if i == 0 else "_nolegend_"
        outline = {"color": "#ff4081", "lw": 0.7, "alpha": 0.6, "zorder": 3, "label": label}
        ax.plot(np.append(c, c[0]), np.append(r, r[0]), "-", **outline)
        dc, dr = _to_px(grid, [fix.pose.lat], [fix.pose.lon])
        points.append((name, float(dc[0]), float(dr[0])))
    if points:
        _, cols, rows = zip(*points, strict=True)
        label = f"under the drone ({len(points)} fixes)"
        ax.plot(cols, rows, "o", color="#00e5ff", ms=5, mec="black", lw=0, zorder=4, label=label)
    sure = [(fix.sigma_m, name, point) for (name, fix), point in zip(accepted, points, strict=True)]
    sure = [entry for entry in sure if entry[0] is not None]
    if len(sure) > 1:
        sigma_m, name, (_, col, row) = max(sure, key=lambda entry: entry[0])
        label = f"least sure fix: {name} (sigma {sigma_m:.1f} m)"
        ax.plot(col, row, "o", ms=14, mfc="none", mec="#ffd600", mew=2, zorder=5, label=label)
    return points


def _draw_rejected(
    ax: Axes, grid: GeoGrid, rejected: list[tuple[str, Fix]], priors: Mapping[str, Prior]
) -> int:
    """An x per rejected frame at its prior position, one colour per reason (the rarer reasons
    as "other"); returns how many had no prior position to be drawn at."""
    placed = [
        (fix, priors[name]) for name, fix in rejected if name in priors and priors[name].lat is not None
    ]
    reasons = [key for key, _ in Counter(_reason_key(fix.reason) for fix, _ in placed).most_common()]
    if len(reasons) > len(REJECTED_COLOURS):
        reasons = reasons[: len(REJECTED_COLOURS) - 1]
    for i, colour in enumerate(REJECTED_COLOURS):
        group = [(fix, p) for fix, p in placed if _reason_group(_reason_key(fix.reason), reasons) == i]
        if not group:
            continue
        what = _reason_range([fix.reason for fix, _ in group]) if i < len(reasons) else "other reasons"
        c, r = _to_px(grid, [p.lat for _, p in group], [p.lon for _, p in group])
        ax.plot(
            c,
            r,
            "x",
            color=colour,
            ms=9,
            mew=2.5,
            lw=0,
            zorder=5,
            path_effects=OUTLINE,
            label=textwrap.fill(f"rejected ({len(group)}), drawn at the prior: {what}", LEGEND_WRAP),
        )
    return len(rejected) - len(placed)


def _reason_key(reason: str) -> str:
    """A rejection reason with its numbers dropped, so frames rejected for one cause group together."""
    return NUMBER.sub("n", reason).strip() or "no reason given"


def _reason_range(reasons: list[str]) -> str:
    """Reasons of one key as one: each number as the range it spans ('only 3-7 inliers (need 12)')."""
    texts = NUMBER.split(reasons[0])
    columns = zip(*([float(v) for v in NUMBER.findall(reason)] for reason in reasons), strict=True)
    spans = [f"{min(c):g}" if min(c) == max(c) else f"{min(c):g}-{max(c):g}" for c in columns]
    return "".join(text + span for text, span in zip(texts, [*spans, ""], strict=True)).strip() or "no reason"


def _reason_group(key: str, reasons: list[str]) -> int:
    return reasons.index(key) if key in reasons else len(reasons)


def _label_points(ax: Axes, points: list[tuple[str, float, float]]) -> None:
    """Name each point where the name covers no earlier name and no marker: tried at four
    offsets, else left out."""
    fig = ax.figure
    fig.canvas.draw()  # final limits and aspect: the labels' extents are where they will be drawn
    renderer = fig.canvas.get_renderer()
    taken = _marker_boxes(ax)
    for name, col, row in points:
        for dx, dy, ha, va in LABEL_OFFSETS:
            text = ax.annotate(
                name,
                (col, row),
                xytext=(dx, dy),
                textcoords="offset points",
                ha=ha,
                va=va,
                fontsize=7,
                color="white",
                path_effects=OUTLINE,
                zorder=6,
            )
            box = text.get_window_extent(renderer)
            if not any(box.overlaps(other) for other in taken):
                taken.append(box)
                break
            text.remove()


def _marker_boxes(ax: Axes) -> list[Bbox]:
    """The display extent of every marker drawn on ``ax`` (lines drawn as markers alone)."""
    boxes = []
    for line in ax.get_lines():
        if line.get_marker() in ("None", "", None) or line.get_linestyle() not in ("None", "", " "):
            continue
        half = line.get_markersize() / 2.0 * ax.figure.dpi / 72.0
        for x, y in ax.transData.transform(np.reshape(line.get_xydata(), (-1, 2))):
            boxes.append(Bbox.from_extents(x - half, y - half, x + half, y + half))
    return boxes


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


def plot_pair_matrix(panels: Mapping[str, list[dict]], out: Path, target: float = 0.9) -> Path:
    """One matrix per method (map rows, frame columns) of the share of frames whose centre was
    fixed within 10 m, coloured, and beside it the share placed there (the pose found, accepted
    or not): a pair's gap between the two is the decision's, the rest of its way to 100 % the
    placement's. ``panels``: label -> bench localize rows with ``map`` and ``frames_from``."""
    fig, axes = plt.subplots(1, len(panels), figsize=(4.6 * len(panels), 4.4), squeeze=False)
    for ax, (label, rows) in zip(axes[0], panels.items(), strict=True):
        names = sorted({r["map"] for r in rows} | {r["frames_from"] for r in rows})
        index = {name: i for i, name in enumerate(names)}
        fixed = np.full((len(names), len(names)), np.nan)
        for r in rows:
            i, j = index[r["map"]], index[r["frames_from"]]
            fixed[i, j] = r["centre_within_10m"]
            text = f"{r['centre_within_10m']:.0%}\n({r['placed_centre_within_10m']:.0%})"
            weight = "bold" if r["centre_within_10m"] >= target else "normal"
            ax.text(j, i, text, ha="center", va="center", fontsize=8, weight=weight)
        ax.imshow(fixed, cmap="RdYlGn", vmin=0.0, vmax=1.0)
        short = [name.rsplit("_", 1)[-1] for name in names]
        ax.set_xticks(range(len(names)), short, rotation=45, fontsize=8)
        ax.set_yticks(range(len(names)), short, fontsize=8)
        ax.set_xlabel("frames of")
        ax.set_ylabel("map of")
        met = sum(r["centre_within_10m"] >= target for r in rows)
        ax.set_title(f"{label}: {met} of {len(rows)} pairs at {target:.0%}", fontsize=9)
    fig.suptitle("frame centre within 10 m: fixed (placed, accepted or not)", fontsize=10)
    fig.tight_layout()
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
    _legend_below(rate_ax, 3)
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
    (keypoints on the index's tiles or on every tile, dense correlation on the index's tiles, the
    cascade)."""
    fig, (recall_ax, copy_ax, fixed_ax, time_ax) = plt.subplots(1, 4, figsize=(24, 4.8))
    k = max(recall_at)
    methods = list(dict.fromkeys(r.get("index", "vlad") for r in rows))
    sources = (("index", "o", "keypoints"), ("all tiles", "s", "keypoints, every tile"))
    sources += (("correlation", "^", "correlation"), ("cascade", "D", "cascade"))
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
    a tick at the median frame's total, for NAIP cross-date frames and for real photos, with the
    accuracy that time bought written at the bar's end; beside them the companion loop's latency
    where the runs measured it, and each run's peak memory."""
    panels = [("NAIP cross-date, 640 x 480", lambda r: r["naip"]["cross-date"], "within_25m", "within 25 m")]
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
        ends = np.fmax(left, np.nan_to_num(medians))
        for yi, r, end in zip(y, rows, ends, strict=True):
            share = part(r).get(key)
            if share is not None:
                ax.text(end, yi, f" {share:.0%} {what}", va="center", fontsize=8)
        ax.set_xlim(0, max(ends.max(), 1.0) * 1.45)
        ax.set_title(title)
        ax.set_xlabel("mean ms per frame by stage; | the median frame")
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
    return _save(fig, out)


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
    return _save(fig, out)
