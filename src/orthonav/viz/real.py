"""The real-photo benchmark at a glance: every run's outcome per photo along the flight, and
where on the orthophoto the photos that fail lie."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.colors import BoundaryNorm, ListedColormap
from matplotlib.patches import Patch, Polygon

from orthonav.geo import GeoRaster, PixelWindow
from orthonav.viz.plots import _save

PREVIEW_PX = 900
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
    coloured by its outcome. Right: the photos and their footprints over the orthophoto, coloured
    by how many runs fixed them, numbered as the columns."""
    runs = len(result["per_photo"])
    fig, (grid_ax, map_ax) = plt.subplots(
        1, 2, figsize=(18, max(6.0, 0.32 * runs + 2.5)), gridspec_kw={"width_ratios": [1.5, 1]}
    )
    _outcomes(grid_ax, result)
    _positions(map_ax, result, ortho)
    fig.suptitle(f"{result['photos']} real photos of {Path(result['dataset']).name}: fixes vs the reference")
    return _save(fig, out)


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
    with GeoRaster(ortho) as raster:
        scale = max(raster.width, raster.height) / PREVIEW_PX
        shape = (round(raster.height / scale), round(raster.width / scale))
        ax.imshow(raster.read_rgb(PixelWindow(0, 0, raster.width, raster.height), out_shape=shape))
        bar_px = 50.0 / raster.gsd_m / scale
        runs = list(result["per_photo"].values())
        lat, lon = np.array([p["reference"] for p in runs[0]], float).T
        col, row = raster.latlon_to_pixel(lat, lon)
        outlines = [
            np.array(raster.latlon_to_pixel(*np.array(f).T)).T / scale for f in result.get("footprints", [])
        ]
    col, row = np.asarray(col) / scale, np.asarray(row) / scale
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
