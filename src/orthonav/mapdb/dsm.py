"""Attaching a DSM/DEM to a map package: read in any CRS and resolution, checked for units and
plausible heights, resampled onto the terrain grid (:mod:`orthonav.mapdb.terrain`, which reads
it back), holes filled where narrow, and recorded in the package's manifest; a corridor's cut
of its parent's terrain likewise."""

from __future__ import annotations

import datetime as dt
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

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
from orthonav.mapdb.package import MANIFEST, MapPackage
from orthonav.mapdb.terrain import TERRAIN

log = logging.getLogger(__name__)

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
