"""Terrain heights of a map package: a DSM/DEM resampled onto the map's work grid.

A pose solved from 2D-3D correspondences needs the height of every map keypoint; on real
photos with relief (trees, houses, slopes) flat ground biases the position by metres. The
heights come from a DSM/DEM GeoTIFF in any CRS and resolution, attached to the package as
``terrain.tif``:

- band 1: height in metres, in the DSM's own vertical datum, NaN where unknown;
- band 2: 1 where the height was filled across a hole of the DSM, 0 where the DSM gave it.

Its grid is the work grid coarsened by a whole factor, so that cells are never finer than
the DSM: upsampling a 30 m DEM to 1 m work pixels would invent no detail and only cost
space. Shares (filled, unknown) are counted over the cells where the map has imagery, so
the no-data surroundings of an orthophoto (and of its DSM) do not count as missing terrain.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import rasterio
from affine import Affine
from pyproj import CRS
from rasterio.errors import RasterioIOError

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.geo import GeoGrid

TERRAIN = "terrain.tif"


def describe(record: dict) -> str:
    """One line: what ``orthonav map terrain`` prints and ``map info`` shows."""
    return (
        f"{record['source']}: {100 * record['cells_filled_frac']:.1f} % of the cells filled, "
        f"{100 * record['unknown_frac']:.1f} % unknown, heights {record['min_m']}..{record['max_m']} m "
        f"(median {record['median_m']} m), {record['cell_m']} m cells"
    )


class Terrain:
    """A package's terrain heights, read-only; ``terrain.tif`` is checked and read on first use."""

    def __init__(self, directory: Path, work: GeoGrid, record: dict) -> None:
        self.file = Path(directory) / record.get("file", TERRAIN)
        self.record = record
        self._work = work
        self._lock = threading.Lock()
        self._data: tuple[GeoGrid, np.ndarray, np.ndarray] | None = None

    @property
    def median_m(self) -> float:
        """Median height of the map's ground: the height of flat ground where none is known."""
        return float(self.record["median_m"])

    @property
    def datum(self) -> str:
        """What the heights are measured from."""
        return str(self.record["datum"])

    def summary(self) -> dict:
        """Where the heights come from and how complete they are, field by field
        (``map info`` shows them in one line, :meth:`describe`)."""
        r = self.record
        return {
            "source": r["source"],
            "source_crs": r["source_crs"],
            "datum": self.datum,
            "vertical_units": r["vertical_units"],
            "cell_m": r["cell_m"],
            "cells_filled": f"{100 * r['cells_filled_frac']:.1f} %",
            "unknown": f"{100 * r['unknown_frac']:.1f} %",
            "heights_m": f"{r['min_m']}..{r['max_m']} (median {r['median_m']})",
        }

    def describe(self) -> str:
        """The summary in one line."""
        return describe(self.record)

    def heights_at(self, map_px: np.ndarray) -> np.ndarray:
        """(N,) heights in metres (in :attr:`datum`) at (N, 2) work-grid pixels (col, row; pixel
        centres at +0.5), bilinear between known cells; NaN off the terrain or where unknown."""
        grid, heights, _ = self._load()
        px = np.asarray(map_px, float).reshape(-1, 2)
        to_cell = ~grid.transform @ self._work.transform
        cols = to_cell.a * px[:, 0] + to_cell.b * px[:, 1] + to_cell.c
        rows = to_cell.d * px[:, 0] + to_cell.e * px[:, 1] + to_cell.f
        return bilinear(heights, cols, rows)

    def heights_at_latlon(self, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """(N,) heights as :meth:`heights_at`, at WGS84 (lat, lon) arrays."""
        col, row = self._work.latlon_to_pixel(lat, lon)
        return self.heights_at(np.column_stack([np.ravel(col), np.ravel(row)]))

    def crop(self, work: GeoGrid) -> tuple[GeoGrid, np.ndarray, np.ndarray]:
        """The grid, heights and filled flags of the cells covering ``work``'s area."""
        grid, heights, filled = self._load()
        xs, ys = work.pixel_to_crs([0, work.width], [0, work.height])
        cols, rows = grid.crs_to_pixel(xs, ys)
        c0, c1 = _span(cols, grid.width)
        r0, r1 = _span(rows, grid.height)
        if c1 <= c0 or r1 <= r0:
            raise OrthonavError(
                f"{self.file}: no terrain cells under the cut ({work.width} x {work.height} px)"
            )
        cut = GeoGrid(grid.crs, grid.transform @ Affine.translation(c0, r0), c1 - c0, r1 - r0)
        return cut, heights[r0:r1, c0:c1], filled[r0:r1, c0:c1]

    def _load(self) -> tuple[GeoGrid, np.ndarray, np.ndarray]:
        with self._lock:  # the companion's threads share one package
            if self._data is None:
                self._data = self._read()
            return self._data

    def _read(self) -> tuple[GeoGrid, np.ndarray, np.ndarray]:
        fix = "re-attach it with `orthonav map terrain`"
        if not self.file.is_file() or sha256_file(self.file) != self.record.get("sha256"):
            raise OrthonavError(f"{self.file}: missing or damaged; {fix}")
        try:
            with rasterio.open(self.file) as ds:
                grid = GeoGrid(CRS.from_user_input(ds.crs), ds.transform, ds.width, ds.height)
                heights, filled = ds.read().astype(np.float32)
        except (RasterioIOError, ValueError) as exc:
            raise OrthonavError(f"{self.file}: unreadable ({exc}); {fix}") from None
        return grid, heights, filled == 1.0


def _span(coords: np.ndarray, size: int) -> tuple[int, int]:
    """Whole cells [first, end) covering continuous coordinates and one more on each side
    (so a cut interpolates up to its edge as the whole did), within 0..size."""
    first = int(np.clip(math.floor(float(coords.min()) + 1e-6) - 1, 0, size))
    end = int(np.clip(math.ceil(float(coords.max()) - 1e-6) + 1, 0, size))
    return first, end


def bilinear(values: np.ndarray, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of a grid at continuous pixel coordinates (centres at +0.5),
    weighting only known neighbours; NaN off the grid or in an unknown cell."""
    h, w = values.shape
    cols, rows = np.asarray(cols, float), np.asarray(rows, float)
    out = np.full(cols.shape, np.nan)
    inside = (cols >= 0) & (cols <= w) & (rows >= 0) & (rows <= h)
    ci = np.clip(np.floor(cols[inside]).astype(int), 0, w - 1)
    ri = np.clip(np.floor(rows[inside]).astype(int), 0, h - 1)
    x = np.clip(cols[inside] - 0.5, 0, w - 1)
    y = np.clip(rows[inside] - 0.5, 0, h - 1)
    x0 = np.minimum(np.floor(x).astype(int), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(int), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    total = np.zeros(len(x))
    weight = np.zeros(len(x))
    for yy, xx, wgt in (
        (y0, x0, (1 - fx) * (1 - fy)),
        (y0, x1, fx * (1 - fy)),
        (y1, x0, (1 - fx) * fy),
        (y1, x1, fx * fy),
    ):
        v = values[yy, xx]
        ok = np.isfinite(v)
        total += np.where(ok, v, 0.0) * wgt
        weight += np.where(ok, wgt, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        result = np.where(np.isfinite(values[ri, ci]) & (weight > 0), total / weight, np.nan)
    out[inside] = result
    return out
