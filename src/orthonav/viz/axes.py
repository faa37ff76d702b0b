"""What every figure shares: maps zoomed to what is drawn, in metres, with a scale bar, a north
arrow and the legend outside; error axes in log metres; the atomic save."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib import patheffects
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter
from matplotlib.transforms import offset_copy
from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

from orthonav.atomic import atomic_path, is_special
from orthonav.errors import OrthonavError
from orthonav.geo import GeoGrid

ZOOM_MARGIN = 0.12  # of the plotted points' extent, on each side of a zoomed map
MIN_MARGIN = 0.04  # of the map's longer side: a short flight still shows the ground around it
MIN_ASPECT = 0.6  # a zoomed view's shorter side, at least, as a share of its longer side
LEGEND_GAP_PT = 40.0  # legends hang this far below their axes, under the tick labels
OUTLINE = [patheffects.withStroke(linewidth=2.5, foreground="black")]
# The scale bar goes in the corner with the fewest plotted points near it (axes fractions).
CORNERS = {"lower left": (0.0, 0.0), "lower right": (1.0, 0.0), "upper left": (0.0, 1.0)}
CORNERS |= {"upper right": (1.0, 1.0)}
CORNER_REACH = (0.3, 0.15)
NORTH_ARROW = 0.08  # the north arrow's length, in axes fractions


def to_px(grid: GeoGrid, lat: Sequence[float], lon: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    col, row = grid.latlon_to_pixel(np.asarray(lat, float), np.asarray(lon, float))
    return np.atleast_1d(col), np.atleast_1d(row)


def save_figure(fig: Figure, out: Path) -> Path:
    """Write atomically, so a reader never sees half a PNG. The format is the suffix's (PNG for
    none), named to matplotlib: it would read the temporary's, and append '.png' to a name
    without one (writing beside ``/dev/null``, not to it). The picture of a result written to a
    device (``bench ... --out /dev/null``, whose picture would be ``/dev/null.png``) is not
    drawn."""
    if out.suffix and is_special(out.with_suffix("")):
        plt.close(fig)
        return out
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


def frame_map(
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
    legend_below(ax, ncol=3)


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
    north_col, north_row = to_px(grid, [float(lat[0]) + 1e-3], [float(lon[0])])
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


def legend_below(ax: Axes, ncol: int) -> None:
    """Under the axes, below their tick labels: a legend inside the data hides what it explains."""
    if not ax.get_legend_handles_labels()[0]:
        return
    below = offset_copy(ax.transAxes, fig=ax.figure, y=-LEGEND_GAP_PT, units="points")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, 0.0), bbox_transform=below, ncol=ncol, fontsize=8)


def log_metres_axis(ax: Axes, floor_m: float) -> None:
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


def log_floor(values: Sequence[float | None]) -> float:
    """The power of ten under the smallest positive value (1 m when there is none)."""
    positive = [v for v in values if v is not None and np.isfinite(v) and v > 0]
    return 10.0 ** math.floor(math.log10(min(positive))) if positive else 1.0
