"""The real-photo benchmark at a glance: every run's outcome per photo along the flight, and
where on the orthophoto the photos that fail lie."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.patches import Patch, Polygon

from orthonav.geo import GeoRaster, PixelWindow
from orthonav.viz.axes import save_figure

PREVIEW_PX = 900  # the longer side of the orthophoto's part drawn, in pixels
MAP_MARGIN = 0.08  # of the photos' extent, around them on the map
# Outcome classes of a photo in one run: rejected, then the error of an accepted fix.
OUTCOMES = (
    ("rejected", "#d9d9d9"),
    ("within 1 m", "#1a9850"),
    ("1-3 m", "#91cf60"),
    ("3-10 m", "#fdae61"),
    ("> 10 m (false)", "#d73027"),
)
EDGES_M = (1.0, 3.0, 10.0)


def plot_real_bench(result: dict, ortho: Path, out: Path) -> Path:
    """Left: one row per run (backend, fix source, variant), one cell per photo in flight order,
    coloured by its outcome. Right: the photos and their footprints over the part of the
    orthophoto they cover, coloured by how many runs fixed them, numbered as the columns.
    Matplotlib's constrained layout keeps the titles, the legend and the colour bar apart."""
    runs = len(result["per_photo"])
    fig, (grid_ax, map_ax) = plt.subplots(
        1,
        2,
        figsize=(18, max(8.0, 0.32 * runs + 3.0)),
        gridspec_kw={"width_ratios": [1.2, 1]},
        layout="constrained",
    )
    _outcomes(grid_ax, result)
    _positions(map_ax, result, ortho)
    fig.suptitle(f"{result['photos']} real photos of {Path(result['dataset']).name}: fixes vs the reference")
    return save_figure(fig, out)


def _outcome_class(photo: dict) -> int:
    """0 rejected, else 1 + how many of EDGES_M the camera position error exceeds."""
    if not photo["accepted"]:
        return 0
    return 1 + int(np.searchsorted(EDGES_M, photo["error_m"], side="left"))


def _outcomes(ax: plt.Axes, result: dict) -> None:
    names = list(result["per_photo"])
    classes = np.array([[_outcome_class(p) for p in photos] for photos in result["per_photo"].values()])
    colours = ListedColormap([colour for _, colour in OUTCOMES])
    norm = BoundaryNorm(np.arange(len(OUTCOMES) + 1) - 0.5, len(OUTCOMES))
    ax.imshow(classes, cmap=colours, norm=norm, aspect="auto", interpolation="nearest")
    labels = []
    for name, row in zip(names, classes, strict=True):
        fixed, within_3 = np.mean(row > 0), np.mean((row == 1) | (row == 2))
        labels.append(f"{name}: {fixed:.0%} fixed, {within_3:.0%} within 3 m")
    ax.set_yticks(range(len(names)), labels, fontsize=8)
    ax.set_xticks(range(0, classes.shape[1], 5))
    ax.set_xticks(np.arange(classes.shape[1] + 1) - 0.5, minor=True)
    ax.set_yticks(np.arange(len(names) + 1) - 0.5, minor=True)
    ax.grid(which="minor", color="white", lw=0.6)
    ax.tick_params(which="minor", length=0)
    ax.set_xlabel("photo, in flight order")
    handles = [Patch(color=colour, label=label) for label, colour in OUTCOMES]
    ax.legend(handles=handles, fontsize=8, ncol=len(OUTCOMES), loc="lower left", bbox_to_anchor=(0.0, 1.0))


def _positions(ax: plt.Axes, result: dict, ortho: Path) -> None:
    runs = list(result["per_photo"].values())
    with GeoRaster(ortho) as raster:
        lat, lon = np.array([p["reference"] for p in runs[0]], float).T
        col, row = (np.asarray(v, float) for v in raster.latlon_to_pixel(lat, lon))
        outlines = [np.array(raster.latlon_to_pixel(*np.array(f).T)).T for f in result.get("footprints", [])]
        window = _around([np.column_stack([col, row]), *outlines], raster.width, raster.height)
        scale = max(window.width, window.height) / PREVIEW_PX
        shape = (round(window.height / scale), round(window.width / scale))
        ax.imshow(raster.read_rgb(window, out_shape=shape))
        bar_px = 50.0 / raster.gsd_m / scale
    # Pixels of the drawn window from here on.
    outlines = [(outline - (window.col0, window.row0)) / scale for outline in outlines]
    col, row = (col - window.col0) / scale, (row - window.row0) / scale
    share = np.mean([[p["accepted"] for p in photos] for photos in runs], axis=0)
    for outline, fixed in zip(outlines, share, strict=False):
        colour = plt.get_cmap("RdYlGn")(fixed)
        ax.add_patch(Polygon(outline, closed=True, fill=False, edgecolor=colour, lw=0.9, alpha=0.7))
    dots = ax.scatter(col, row, c=share, cmap="RdYlGn", vmin=0.0, vmax=1.0, s=60, edgecolors="black", lw=0.5)
    for i, (x, y) in enumerate(zip(col, row, strict=True)):
        ax.annotate(str(i), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, color="white")
    ax.plot([20, 20 + bar_px], [shape[0] - 25] * 2, color="white", lw=3)
    ax.text(20, shape[0] - 35, "50 m", color="white", fontsize=9)
    ax.set_axis_off()
    ax.set_title(
        "reference cameras and footprints, by the share of runs that fixed them\n(numbered as the columns)"
    )
    plt.colorbar(dots, ax=ax, fraction=0.04, pad=0.02, label="share of runs with a fix")


def _around(points: list[np.ndarray], width: int, height: int) -> PixelWindow:
    """The orthophoto's window around every photo and footprint, with a margin, within the
    raster: a flight over a corner of a large orthophoto is not drawn as a speck."""
    xy = np.concatenate([np.reshape(p, (-1, 2)) for p in points])
    low, high = xy.min(axis=0), xy.max(axis=0)
    margin = MAP_MARGIN * float(max(high - low)) + 1.0
    col0, row0 = (max(0, int(v - margin)) for v in low)
    col1, row1 = min(width, int(high[0] + margin) + 1), min(height, int(high[1] + margin) + 1)
    return PixelWindow(col0, row0, max(col1 - col0, 1), max(row1 - row0, 1))
