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
from orthonav.localize import Fix
from orthonav.mapdb import MapPackage


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
    package: MapPackage, steps: list[dict], start: tuple[float, float], target: tuple[float, float], out: Path
) -> Path:
    """ "Drone Trajectory on GeoTIFF Map": true track, fixes, rejected steps, start/end/target."""
    image, grid = package.preview()
    fig, ax = plt.subplots(figsize=(9, 9 * image.shape[0] / image.shape[1]))
    ax.imshow(image)
    tc, tr = _to_px(grid, [s["true_lat"] for s in steps], [s["true_lon"] for s in steps])
    ax.plot(tc, tr, "-", color="#00e5ff", lw=2, label="true track")
    fixes = [s for s in steps if s["accepted"]]
    if fixes:
        ec, er = _to_px(grid, [s["est_lat"] for s in fixes], [s["est_lon"] for s in fixes])
        ax.plot(ec, er, "o--", color="#ff4081", ms=4, lw=1, label=f"estimated ({len(fixes)} fixes)")
    rejected = [s for s in steps if not s["accepted"]]
    if rejected:
        rc, rr = _to_px(grid, [s["true_lat"] for s in rejected], [s["true_lon"] for s in rejected])
        ax.plot(rc, rr, "x", color="#ffd600", ms=8, mew=2, label=f"rejected fix ({len(rejected)})")
    for (lat, lon), marker, colour, label in (
        (start, "^", "#76ff03", "start"),
        ((steps[-1]["true_lat"], steps[-1]["true_lon"]), "s", "#ffffff", "end (true)"),
        (target, "*", "#ff1744", "target"),
    ):
        c, r = _to_px(grid, [lat], [lon])
        ax.plot(c, r, marker, color=colour, ms=14, mec="black", label=label)
    ax.set_title("Drone Trajectory on GeoTIFF Map")
    ax.set_xlim(0, image.shape[1])
    ax.set_ylim(image.shape[0], 0)
    ax.set_axis_off()
    ax.legend(loc="lower right", fontsize=8, framealpha=0.8)
    return _save(fig, out)


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
