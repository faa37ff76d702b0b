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

import datetime as dt
import json
import logging
import math
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rasterio
import rasterio.crs
import rasterio.fill
import rasterio.warp
import rasterio.windows
from affine import Affine
from pyproj import CRS
from rasterio.enums import Resampling
from rasterio.errors import RasterioError, RasterioIOError, WindowError
from tqdm import tqdm

from orthonav.atomic import sha256_file, write_text_atomic
from orthonav.errors import OrthonavError
from orthonav.geo import GeoGrid, bright_pixels, write_geotiff
from orthonav.mapdb.package import MANIFEST

if TYPE_CHECKING:
    from orthonav.mapdb.package import MapPackage

log = logging.getLogger(__name__)

TERRAIN = "terrain.tif"
PLAUSIBLE_M = (-500.0, 9000.0)  # below the Dead Sea shore .. above Everest
MAX_FILL_M = 50.0  # holes are filled from up to this far away; wider ones stay unknown
MAX_UNKNOWN_FRAC = 0.5
IMAGERY_MIN = 10  # preview pixels darker than this in every band are no-data surroundings
FEET = ("foot", "feet", "ft")
METRES = ("m", "metre", "meter", "metres", "meters")


# --- reading a DSM ------------------------------------------------------------------------------


@dataclass(frozen=True)
class DsmWindow:
    """Band 1 of a DSM over the map's area: heights (NaN unknown) with their georeferencing."""

    path: Path
    crs: CRS  # horizontal part of the DSM's CRS
    vertical: str | None  # name of its vertical CRS, when the file declares one
    transform: Affine
    heights: np.ndarray
    gsd_m: float  # the DSM's own cell size on the ground


def read_dsm(dsm: Path, work: GeoGrid) -> DsmWindow:
    """The DSM over the work grid's area; read at about half the terrain cell when it is
    much finer, so a centimetre DSM under a large map does not have to fit in memory."""
    with _open_dsm(dsm) as ds:
        _check_units(dsm, ds)
        crs = CRS.from_user_input(ds.crs)
        horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
        vertical = crs.sub_crs_list[1].name if crs.is_compound and len(crs.sub_crs_list) > 1 else None
        window = _map_window(dsm, ds, work)
        transform = ds.window_transform(window)
        gsd_m = GeoGrid(horizontal, transform, int(window.width), int(window.height)).gsd_m
        step = max(1, int(terrain_grid(work, gsd_m).gsd_m / gsd_m / 2.0))
        shape = (max(1, math.ceil(window.height / step)), max(1, math.ceil(window.width / step)))
        try:
            band = ds.read(1, window=window, out_shape=shape, masked=True, resampling=Resampling.average)
        except RasterioError as exc:
            raise OrthonavError(f"{dsm}: heights unreadable over the map's area ({exc})") from None
        band = band.astype(np.float64) * (ds.scales[0] or 1.0) + (ds.offsets[0] or 0.0)  # packed DEMs
        transform = transform @ Affine.scale(window.width / shape[1], window.height / shape[0])
    heights = _plausible(dsm, np.ma.filled(band, np.nan).astype(np.float32))
    return DsmWindow(dsm, horizontal, vertical, transform, heights, gsd_m)


def _open_dsm(dsm: Path) -> rasterio.DatasetReader:
    if not dsm.is_file():
        raise OrthonavError(f"{dsm}: no such file (expected a DSM/DEM GeoTIFF of heights in metres)")
    try:
        ds = rasterio.open(dsm)
    except RasterioIOError as exc:
        raise OrthonavError(f"{dsm}: not a readable DSM/DEM GeoTIFF ({exc})") from None
    if ds.crs is None:
        ds.close()
        raise OrthonavError(f"{dsm}: has no coordinate reference system (expected a georeferenced DSM/DEM)")
    if not np.issubdtype(np.dtype(ds.dtypes[0]), np.number) or np.dtype(ds.dtypes[0]).kind == "c":
        ds.close()
        raise OrthonavError(f"{dsm}: pixel type {ds.dtypes[0]}, expected heights (integers or floats)")
    return ds


def _is_feet(unit: str | None) -> bool:
    """Whether a unit name is a foot of any kind (foot, US survey foot, ft, us-ft, ...)."""
    unit = (unit or "").strip().lower()
    return any(word in unit for word in FEET)


def _check_units(dsm: Path, ds: rasterio.DatasetReader) -> None:
    """Heights must be metres: a band unit of feet is refused, and so is a vertical CRS in
    feet or, without one, a horizontal CRS in feet (its heights usually are too); a band that
    says metres is believed over its CRS."""
    band_unit = (ds.units[0] or "").strip()
    if band_unit.lower() in METRES:
        return
    if _is_feet(band_unit):
        problem = f"its band unit is {band_unit!r}"
    else:
        crs = CRS.from_user_input(ds.crs)
        measured = crs.sub_crs_list[-1] if crs.is_compound else crs
        feet = [axis.unit_name for axis in measured.axis_info if _is_feet(axis.unit_name)]
        if not feet:
            return
        problem = f"its CRS {measured.name} is in {feet[0]}"
    raise OrthonavError(
        f"{dsm}: {problem}; expected heights in metres (convert the DSM to metres and a metre CRS "
        "first, e.g. with gdal_calc.py and gdalwarp)"
    )


def _map_window(dsm: Path, ds: rasterio.DatasetReader, grid: GeoGrid) -> rasterio.windows.Window:
    """The DSM's pixels under the map (2 cells of margin for the interpolation), or an error."""
    xs, ys = grid.pixel_to_crs([0, grid.width], [grid.height, 0])
    dst_crs = rasterio.crs.CRS.from_wkt(grid.crs.to_wkt())
    try:
        bounds = rasterio.warp.transform_bounds(dst_crs, ds.crs, xs[0], ys[0], xs[1], ys[1], densify_pts=21)
        exact = rasterio.windows.from_bounds(*bounds, transform=ds.transform)
    except (ValueError, RasterioError) as exc:
        raise OrthonavError(f"{dsm}: its CRS cannot be related to the map's ({exc})") from None
    col0, row0 = math.floor(exact.col_off) - 2, math.floor(exact.row_off) - 2
    col1 = math.ceil(exact.col_off + exact.width) + 2
    row1 = math.ceil(exact.row_off + exact.height) + 2
    full = rasterio.windows.Window(0, 0, ds.width, ds.height)
    try:
        return rasterio.windows.Window(col0, row0, col1 - col0, row1 - row0).intersection(full)
    except WindowError:
        left, bottom, right, top = ds.bounds
        raise OrthonavError(
            f"{dsm}: does not overlap the map (the DSM covers x {left:.1f}..{right:.1f}, "
            f"y {bottom:.1f}..{top:.1f} in {CRS.from_user_input(ds.crs).to_string()}; the map "
            f"x {xs[0]:.1f}..{xs[1]:.1f}, y {ys[0]:.1f}..{ys[1]:.1f} in {grid.crs.to_string()})"
        ) from None


def _plausible(dsm: Path, heights: np.ndarray) -> np.ndarray:
    """Values that cannot be metres above a datum (an undeclared nodata such as -32768, or a
    DSM in millimetres) are unknown; a DSM with none plausible is refused."""
    known = np.isfinite(heights)
    if not known.any():
        raise OrthonavError(f"{dsm}: has no heights over the map's area (only nodata there)")
    lo, hi = PLAUSIBLE_M
    with np.errstate(invalid="ignore"):
        bad = known & ((heights < lo) | (heights > hi))
    if bad.all(where=known):
        raise OrthonavError(
            f"{dsm}: heights {np.nanmin(heights):.6g}..{np.nanmax(heights):.6g} over the map are not "
            f"plausible (expected heights in metres, {lo:g}..{hi:g})"
        )
    if bad.any():
        log.warning("%s: %d cells outside %g..%g m treated as unknown", dsm, int(bad.sum()), lo, hi)
    return np.where(bad, np.float32(np.nan), heights)


# --- the terrain grid ---------------------------------------------------------------------------


def terrain_grid(work: GeoGrid, dsm_gsd_m: float) -> GeoGrid:
    """The work grid coarsened by a whole factor to about the DSM's cell size; it covers the
    whole work grid (sizes rounded up) and keeps at least 2 x 2 cells."""
    factor = max(1, int(dsm_gsd_m / work.gsd_m + 1e-6))
    factor = min(factor, max(1, min(work.width, work.height) // 2))
    return GeoGrid(
        work.crs,
        work.transform @ Affine.scale(factor),
        math.ceil(work.width / factor),
        math.ceil(work.height / factor),
    )


def resample(source: DsmWindow, grid: GeoGrid) -> np.ndarray:
    """The DSM on ``grid`` (bilinear), NaN where it has no heights."""
    out = np.full((grid.height, grid.width), np.nan, np.float32)
    rasterio.warp.reproject(
        source.heights,
        out,
        src_transform=source.transform,
        src_crs=rasterio.crs.CRS.from_wkt(source.crs.to_wkt()),
        src_nodata=np.nan,
        dst_transform=grid.transform,
        dst_crs=rasterio.crs.CRS.from_wkt(grid.crs.to_wkt()),
        dst_nodata=np.nan,
        resampling=Resampling.bilinear,
    )
    return out


def fill_holes(heights: np.ndarray, max_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """Holes filled by GDAL's inverse-distance fill from at most ``max_cells`` away (wider
    ones stay NaN); returns the heights and where they were filled."""
    known = np.isfinite(heights)
    if known.all():
        return heights, np.zeros(heights.shape, bool)
    out = rasterio.fill.fillnodata(
        heights.copy(), mask=known.astype(np.uint8), max_search_distance=max(1.0, max_cells)
    ).astype(np.float32)
    return out, ~known & np.isfinite(out)


def imagery_mask(preview: tuple[np.ndarray, GeoGrid] | None, grid: GeoGrid) -> np.ndarray:
    """Terrain cells where the map has imagery, from a preview of the orthophoto (RGB and its
    grid; all cells when there is none: then every cell counts)."""
    if preview is None:
        return np.ones((grid.height, grid.width), bool)
    image, preview_grid = preview
    # Both grids are north-up in the map's CRS: columns and rows map independently.
    xs, _ = grid.pixel_to_crs(np.arange(grid.width) + 0.5, 0.5)
    _, ys = grid.pixel_to_crs(0.5, np.arange(grid.height) + 0.5)
    pc, _ = preview_grid.crs_to_pixel(xs, ys[0])
    _, pr = preview_grid.crs_to_pixel(xs[0], ys)
    pc = np.clip(np.floor(pc).astype(int), 0, image.shape[1] - 1)
    pr = np.clip(np.floor(pr).astype(int), 0, image.shape[0] - 1)
    return bright_pixels(image, IMAGERY_MIN)[np.ix_(pr, pc)]


# --- the manifest record ------------------------------------------------------------------------


def terrain_stats(heights: np.ndarray, filled: np.ndarray, imagery: np.ndarray) -> dict:
    """Shares of filled and unknown cells among those with imagery, and the height range."""
    counted = imagery if imagery.any() else np.ones_like(imagery)
    known = np.isfinite(heights)
    values = heights[known & counted] if (known & counted).any() else heights[known]
    n = int(counted.sum())
    return {
        "cells_filled_frac": round(float((filled & counted).sum()) / n, 4),
        "unknown_frac": round(float((~known & counted).sum()) / n, 4),
        "min_m": round(float(values.min()), 2) if len(values) else None,
        "median_m": round(float(np.median(values)), 2) if len(values) else None,
        "max_m": round(float(values.max()), 2) if len(values) else None,
        "shares_of": "cells with imagery" if imagery.any() else "all cells",
    }


def describe(record: dict) -> str:
    """One line: what ``orthonav map terrain`` prints and ``map info`` shows."""
    return (
        f"{record['source']}: {100 * record['cells_filled_frac']:.1f} % of the cells filled, "
        f"{100 * record['unknown_frac']:.1f} % unknown, heights {record['min_m']}..{record['max_m']} m "
        f"(median {record['median_m']} m), {record['cell_m']} m cells"
    )


def _write(file: Path, grid: GeoGrid, heights: np.ndarray, filled: np.ndarray) -> None:
    """``terrain.tif`` (heights, filled flags), atomically."""
    flags = np.where(np.isfinite(heights), filled.astype(np.float32), np.float32(np.nan))
    tiled = grid.width >= 256 and grid.height >= 256
    profile = {
        "driver": "GTiff",
        "width": grid.width,
        "height": grid.height,
        "count": 2,
        "dtype": "float32",
        "crs": rasterio.crs.CRS.from_wkt(grid.crs.to_wkt()),
        "transform": grid.transform,
        "nodata": np.nan,
        "compress": "deflate",
        "predictor": 3,
        **({"tiled": True, "blockxsize": 256, "blockysize": 256} if tiled else {}),
    }
    write_geotiff(file, np.stack([heights, flags]).astype(np.float32), profile)


def _store(package: MapPackage, grid: GeoGrid, heights: np.ndarray, filled: np.ndarray, record: dict) -> None:
    """Write ``terrain.tif``, then the manifest naming it with ``record`` (each atomically);
    replaces any previous terrain."""
    file = package.path / TERRAIN
    _write(file, grid, heights, filled)
    record = {"file": TERRAIN, "sha256": sha256_file(file), **record}
    manifest = {**package.manifest, "terrain": record}
    write_text_atomic(package.path / MANIFEST, json.dumps(manifest, indent=2))


# --- attaching and cutting ----------------------------------------------------------------------


@dataclass(frozen=True)
class PreparedTerrain:
    """A DSM resampled onto a map's terrain grid and checked, ready to be stored in the package."""

    source: DsmWindow
    grid: GeoGrid
    heights: np.ndarray
    filled: np.ndarray
    max_fill_m: float


def prepare_terrain(
    dsm: Path, work: GeoGrid, preview: tuple[np.ndarray, GeoGrid] | None, max_fill_m: float = MAX_FILL_M
) -> PreparedTerrain:
    """Read the DSM over the work grid, resample it, fill its holes up to ``max_fill_m`` from known
    heights, and refuse it (one line naming the file) when it cannot serve the map. A map build
    calls this before its tiles, so that a wrong DSM fails before the long part of the build;
    ``preview``: the orthophoto's preview, whose imagery decides which cells must have heights."""
    source = read_dsm(dsm, work)
    grid = terrain_grid(work, source.gsd_m)
    heights = resample(source, grid)
    if not np.isfinite(heights).any():
        raise OrthonavError(f"{dsm}: has no heights over the map's area (only nodata there)")
    heights, filled = fill_holes(heights, max_fill_m / grid.gsd_m)
    stats = terrain_stats(heights, filled, imagery_mask(preview, grid))
    if stats["unknown_frac"] > MAX_UNKNOWN_FRAC:
        raise OrthonavError(
            f"{dsm}: {100 * stats['unknown_frac']:.0f} % of the map's {stats['shares_of']} have no "
            f"height even after filling holes from up to {max_fill_m:g} m away (at most "
            f"{100 * MAX_UNKNOWN_FRAC:.0f} % allowed); expected a DSM covering the map"
        )
    return PreparedTerrain(source, grid, heights, filled, max_fill_m)


def store_terrain(package: MapPackage, terrain: PreparedTerrain) -> MapPackage:
    """Store prepared terrain as the package's (replacing any before); returns it reopened."""
    stats = terrain_stats(terrain.heights, terrain.filled, imagery_mask(_preview(package), terrain.grid))
    record = {**_source_record(terrain.source, terrain.grid, package.grid, terrain.max_fill_m), **stats}
    _store(package, terrain.grid, terrain.heights, terrain.filled, record)
    return type(package)(package.path)


def attach_terrain(
    package: MapPackage, dsm: Path, progress: bool = False, *, max_fill_m: float = MAX_FILL_M
) -> MapPackage:
    """Resample a DSM/DEM onto the package's grid, fill its holes up to ``max_fill_m`` from
    known heights, store it as the package's terrain and return the package reopened."""
    with tqdm(total=2, desc="terrain", unit="step", disable=not progress) as bar:
        prepared = prepare_terrain(Path(dsm), package.grid, _preview(package), max_fill_m)
        bar.update()
        package = store_terrain(package, prepared)
        bar.update()
    return package


def _preview(package: MapPackage) -> tuple[np.ndarray, GeoGrid] | None:
    """The package's preview, or None when it cannot be read (then every terrain cell counts)."""
    try:
        return package.preview()
    except OrthonavError:
        return None


def _source_record(source: DsmWindow, grid: GeoGrid, work: GeoGrid, max_fill_m: float) -> dict:
    name = source.path.name
    datum = source.vertical or "the DSM's vertical datum"
    return {
        "source": name,
        "source_path": str(source.path.resolve()),
        "source_crs": source.crs.to_string(),
        "source_gsd_m": round(source.gsd_m, 4),
        "vertical_units": "m",
        "datum": f"{datum} (source: {name})",
        "cell_m": round(grid.gsd_m, 4),
        "cell_work_px": round(grid.transform.a / work.transform.a),
        "width": grid.width,
        "height": grid.height,
        "max_fill_m": max_fill_m,
        "attached": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
    }


def cut_terrain(parent: MapPackage, child: MapPackage) -> MapPackage:
    """Give ``child`` (a cut of ``parent`` in the same CRS, e.g. a corridor) the parent's
    terrain cells that cover its work grid, unchanged; returns ``child`` reopened."""
    terrain = parent.terrain
    if terrain is None:
        return child
    grid, heights, filled = terrain.crop(child.grid)
    record = {k: v for k, v in parent.manifest["terrain"].items() if k not in ("file", "sha256")}
    record.update(width=grid.width, height=grid.height, cut_from=str(parent.path.resolve()))
    record.update(terrain_stats(heights, filled, imagery_mask(_preview(child), grid)))
    _store(child, grid, heights, filled, record)
    return type(child)(child.path)


# --- reading ------------------------------------------------------------------------------------


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
