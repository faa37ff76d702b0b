"""The real-photo benchmark at a glance: error per photo along the flight, and where the fixes
fell over the orthophoto."""

from __future__ import annotations

from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.ticker import LogLocator

from orthonav.geo import GeoRaster, PixelWindow
from orthonav.viz.plots import _save

PREVIEW_PX = 900


def plot_real_bench(result: dict, ortho: Path, out: Path) -> Path:
    """Left: each photo's error (log scale) in flight order per backend and variant, rejected
    photos as crosses on the top edge. Right: reference positions and fixes over the ortho."""
    fig, (err_ax, map_ax) = plt.subplots(1, 2, figsize=(17, 7), gridspec_kw={"width_ratios": [1.4, 1]})
    _errors(err_ax, result)
    _positions(map_ax, result, ortho)
    fig.suptitle(f"{result['photos']} real photos of {Path(result['dataset']).name}: fixes vs the reference")
    return _save(fig, out)


def _errors(ax: plt.Axes, result: dict) -> None:
    top = 100.0
    for key, photos in result["per_photo"].items():
        x = np.arange(len(photos))
        errors = np.array([p["error_m"] if p["accepted"] else np.nan for p in photos], float)
        (line,) = ax.plot(x, errors, marker="o", ms=3.5, lw=0.8, label=key)
        rejected = x[np.isnan(errors)]
        ax.plot(rejected, np.full(len(rejected), top * 0.9), "x", color=line.get_color(), ms=5)
    ax.set_yscale("log")
    ax.set_ylim(0.02, top)
    ax.yaxis.set_minor_locator(LogLocator(subs="all"))
    ax.axhline(3.0, color="0.4", ls="--", lw=0.8)
    ax.text(0, 3.3, "3 m", color="0.3", fontsize=8)
    ax.set_xlabel("photo, in flight order (x on top: rejected)")
    ax.set_ylabel("camera position error vs the reference (m)")
    ax.grid(which="both", alpha=0.25)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))


def _positions(ax: plt.Axes, result: dict, ortho: Path) -> None:
    with GeoRaster(ortho) as raster:
        scale = max(raster.width, raster.height) / PREVIEW_PX
        shape = (round(raster.height / scale), round(raster.width / scale))
        ax.imshow(raster.read_rgb(PixelWindow(0, 0, raster.width, raster.height), out_shape=shape))
        bar_px = 50.0 / raster.gsd_m / scale

        def px(lat_lon: list) -> tuple[np.ndarray, np.ndarray]:
            lat, lon = np.array(lat_lon, float).reshape(-1, 2).T
            col, row = raster.latlon_to_pixel(lat, lon)
            return np.asarray(col) / scale, np.asarray(row) / scale

        photos = next(iter(result["per_photo"].values()))
        ax.plot(*px([p["reference"] for p in photos]), "o", mfc="none", mec="lime", ms=7, label="reference")
        for key, photos in result["per_photo"].items():
            fixed = [p["position"] for p in photos if p["accepted"]]
            if fixed:
                ax.plot(*px(fixed), ".", ms=5, label=f"fixes: {key}")
            lost = [p["reference"] for p in photos if not p["accepted"]]
            if lost:
                ax.plot(*px(lost), "x", color="red", ms=6)
    ax.plot([20, 20 + bar_px], [shape[0] - 25] * 2, color="white", lw=3)
    ax.text(20, shape[0] - 35, "50 m", color="white", fontsize=9)
    ax.set_axis_off()
    ax.set_title("reference cameras (green), fixes (dots), rejected (red x)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
