"""``localize --plot``: the fixes and the rejected frames over the map."""

from __future__ import annotations

import re
import textwrap
from collections import Counter
from collections.abc import Mapping
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.transforms import Bbox

from orthonav.camera import Camera
from orthonav.geo import GeoGrid
from orthonav.mapdb import MapPackage
from orthonav.types import Fix, Prior
from orthonav.viz.axes import OUTLINE, frame_map, save_figure, to_px

# Rejected frames: one colour per reason, the rarer reasons together in the last.
REJECTED_COLOURS = ("#ffd600", "#ff9100", "#ff1744", "#e040fb")
# Where a frame's name may go around its point: (dx, dy) in points and the text's alignment.
LABEL_OFFSETS = ((4, 4, "left", "bottom"), (4, -4, "left", "top"), (-4, 4, "right", "bottom"))
LABEL_OFFSETS += ((-4, -4, "right", "top"),)
LEGEND_WRAP = 44  # characters per line of a legend entry: wrapped, never cut
NUMBER = re.compile(r"\d+(?:\.\d+)?")


def plot_fixes(
    package: MapPackage,
    fixes: list[tuple[str, Fix]],
    camera: Camera,
    out: Path,
    priors: Mapping[str, Prior] | None = None,
) -> Path:
    """Localized and rejected frames over the map (see :func:`fixes_figure`)."""
    return save_figure(fixes_figure(package, fixes, camera, priors), out)


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
    frame_map(ax, image.shape, grid, centre, "the map centre")
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
        c, r = to_px(grid, corners[:, 0], corners[:, 1])
        label = "camera footprint" if i == 0 else "_nolegend_"
        outline = {"color": "#ff4081", "lw": 0.7, "alpha": 0.6, "zorder": 3, "label": label}
        ax.plot(np.append(c, c[0]), np.append(r, r[0]), "-", **outline)
        dc, dr = to_px(grid, [fix.pose.lat], [fix.pose.lon])
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
        c, r = to_px(grid, [p.lat for _, p in group], [p.lon for _, p in group])
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
