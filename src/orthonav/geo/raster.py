"""Opening and validating georeferenced orthophotos, and pixel <-> CRS <-> WGS84 transforms.

Pixel coordinates are (col, row) with the origin at the top-left corner of the top-left
pixel (rasterio's convention): the centre of pixel (0, 0) is (0.5, 0.5).
"""

from __future__ import annotations

import math
import os
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import rasterio
import rasterio.windows
from affine import Affine
from pyproj import CRS
from rasterio.enums import ColorInterp, Resampling
from rasterio.errors import NotGeoreferencedWarning, RasterioIOError
from rasterio.windows import Window

from orthonav.atomic import atomic_path
from orthonav.errors import OrthonavError
from orthonav.geo.grid import GeoGrid

MIN_GSD_M = 0.001
MAX_GSD_M = 1000.0
SUPPORTED_DTYPES = ("uint8", "uint16", "int16", "float32", "float64")
OVERVIEW_PX = 512
VIEW_GRID = 7
BLOCK_CACHE_BYTES = 64 * 2**20
# Views are cut from an in-memory copy of the whole raster, at the coarsest power-of-two level
# that is no coarser than the view, where that copy takes at most this much memory.
VIEW_CACHE_BYTES = 96 * 2**20
# The water mask is read at most this many pixels across: finer than a lake's edge moves between years.
WATER_MASK_MAX_PX = 4096
MAX_VIEW_LEVEL = 64

# Output pixels (N, 2) (x, y), origin at the top-left corner of the image -> WGS84 (lat, lon).
PixelToLatLon = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@contextmanager
def bounded_block_cache(max_bytes: int = BLOCK_CACHE_BYTES) -> Iterator[None]:
    """GDAL's raster block cache capped at ``max_bytes`` inside the block.

    GDAL keeps every block it decodes up to 5 % of the machine's RAM by default, so reading
    a large mosaic window by window would grow with the map; capped, a map build holds
    constant memory at a small cost in re-decoded blocks. A ``GDAL_CACHEMAX`` set in the
    environment is left as the user chose it.
    """
    if "GDAL_CACHEMAX" in os.environ:
        yield
        return
    with rasterio.Env(GDAL_CACHEMAX=max_bytes):
        yield


@dataclass(frozen=True)
class PixelWindow:
    """A rectangle of raster pixels: top-left (col0, row0), size (width, height).

    Fractional values are honoured (GDAL resamples), so a window on a coarser work grid
    reads exactly the ground it covers.
    """

    col0: float
    row0: float
    width: float
    height: float


class GeoRaster(GeoGrid):
    """A validated, north-up GeoTIFF orthophoto with its geo transforms.

    Images are returned as uint8 RGB (or gray): other bit depths are stretched to 8 bits
    with one set of percentiles per raster, so every window of a map looks the same. Views
    (:meth:`read_view`) are cut from copies of the whole raster kept in memory, each level up
    to ``view_cache_bytes`` (0: every view read from the file).
    """

    def __init__(self, path: str | Path, view_cache_bytes: int = VIEW_CACHE_BYTES) -> None:
        self.path = Path(path)
        if view_cache_bytes < 0:
            raise OrthonavError(
                f"{self.path}: view_cache_bytes {view_cache_bytes}: expected bytes >= 0 "
                "(0: no views in memory)"
            )
        self.view_cache_bytes = view_cache_bytes
        self._levels: dict[int, np.ndarray] = {}
        self._ds = _open_dataset(self.path)
        ds = self._ds
        super().__init__(CRS.from_user_input(ds.crs), ds.transform, ds.width, ds.height)
        self.band_count: int = ds.count
        self.dtype: str = ds.dtypes[0]
        self.nodata = ds.nodata
        _check_transform(self.path, self.transform)
        _check_coordinates(self)
        try:
            self._stretch = _stretch_limits(self)
        except RasterioIOError as exc:
            ds.close()
            raise OrthonavError(
                f"{self.path}: its pixels cannot be read ({exc}): a truncated or damaged file?"
            ) from None

    # --- pixels ------------------------------------------------------------------------
    def read_rgb(
        self, window: PixelWindow | None = None, out_shape: tuple[int, int] | None = None
    ) -> np.ndarray:
        """Read (H, W, 3) uint8 RGB; pixels outside the raster or nodata are 0.

        ``out_shape`` (rows, cols) resamples with area averaging, for reading a window at a
        coarser ground resolution without aliasing.
        """
        window = window or PixelWindow(0, 0, self.width, self.height)
        bands = [1, 2, 3] if self.band_count >= 3 else [1]
        shape = out_shape or (round(window.height), round(window.width))
        try:
            data = self._ds.read(
                bands,
                window=Window(window.col0, window.row0, window.width, window.height),
                out_shape=(len(bands), *shape),
                boundless=True,  # no fill_value: it would replace the nodata value in the masks
                resampling=Resampling.average if out_shape else Resampling.nearest,
                masked=True,
            )
        except RasterioIOError as exc:
            cols = f"{window.col0:.0f}..{window.col0 + window.width:.0f}"
            rows = f"{window.row0:.0f}..{window.row0 + window.height:.0f}"
            raise OrthonavError(
                f"{self.path}: cannot read the pixels of columns {cols}, rows {rows} ({exc}): "
                "a truncated or damaged file?"
            ) from None
        # A pixel is nodata when every band read is (GDAL masks each band on its own).
        invalid = np.ma.getmaskarray(data).all(axis=0)
        rgb = _to_uint8(np.ma.getdata(data), self._stretch)
        rgb[:, invalid] = 0
        if rgb.shape[0] == 1:
            rgb = np.repeat(rgb, 3, axis=0)
        return np.ascontiguousarray(np.moveaxis(rgb, 0, -1))

    def read_grid_box(self, grid: GeoGrid, box: tuple[float, float, float, float]) -> np.ndarray:
        """RGB of the ground that pixel box (col0, row0, col1, row1) of ``grid`` covers, sampled
        to the box's size (area averaging).

        On a grid that is this raster scaled (the work grid of a map build) the window is the
        box times the scale factor, exactly; on any other grid of the same CRS it goes through
        the CRS coordinates of the box's corners.
        """
        col0, row0, col1, row1 = (float(v) for v in box)
        out_shape = (round(row1 - row0), round(col1 - col0))
        factor = self.scale_factor_of(grid)
        if factor is not None:
            window = PixelWindow(col0 * factor, row0 * factor, (col1 - col0) * factor, (row1 - row0) * factor)
            return self.read_rgb(window, out_shape=out_shape)
        if not CRS.from_user_input(grid.crs).equals(self.crs):
            raise OrthonavError(f"{self.path}: grid CRS {grid.crs} differs from the raster's {self.crs}")
        xs, ys = grid.pixel_to_crs(np.array([col0, col1]), np.array([row0, row1]))
        cols, rows = self.crs_to_pixel(xs, ys)
        window = PixelWindow(cols[0], rows[0], cols[1] - cols[0], rows[1] - rows[0])
        return self.read_rgb(window, out_shape=out_shape)

    def scale_factor_of(self, grid: GeoGrid) -> float | None:
        """``f`` when ``grid`` is this raster's grid with pixels ``f`` times larger (same CRS and
        origin), else None."""
        t, g = self.transform, grid.transform
        factor = g.a / t.a
        if not CRS.from_user_input(grid.crs).equals(self.crs):
            return None
        expected = t @ Affine.scale(factor)
        tol = 1e-9 * max(abs(t.a), abs(t.e))
        if all(abs(u - v) <= tol * (1 + abs(v)) for u, v in zip(g[:6], expected[:6], strict=True)):
            return factor
        return None

    def read_view_window(
        self, out_to_latlon: PixelToLatLon, width: int, height: int, gsd_m: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The window an output image of ``width`` x ``height`` px looks at, and where.

        The window is read at about ``gsd_m`` (area averaging, so a coarse view does not alias).
        Returns (window RGB, 3x3 homography from output pixel coordinates to window OpenCV
        coordinates), fitted on a grid: exact for any view of a flat ground.
        """
        rgb, (h_out_to_window,) = self._read_shared_window([(out_to_latlon, width, height)], gsd_m)
        return rgb, h_out_to_window

    def _read_shared_window(
        self, outputs: Sequence[tuple[PixelToLatLon, int, int]], gsd_m: float
    ) -> tuple[np.ndarray, list[np.ndarray]]:
        """One window for several outputs (``out_to_latlon``, width, height) at one resolution,
        read once, with each output's homography into it: views of one place at several headings
        overlap mostly, and reading and area-averaging the window is most of a view's cost."""
        grids, pixels = [], []
        for out_to_latlon, width, height in outputs:
            gu, gv = np.meshgrid(np.linspace(0, width, VIEW_GRID), np.linspace(0, height, VIEW_GRID))
            grid_px = np.column_stack([gu.ravel(), gv.ravel()])
            grids.append(grid_px)
            pixels.append(np.column_stack(self.latlon_to_pixel(*out_to_latlon(grid_px))))
        col, row = np.concatenate(pixels).T
        decimate = max(1.0, gsd_m / self.gsd_m)
        level = self._view_level(decimate)
        step = level or 1  # the window on whole pixels of the level it is cut from
        c0, r0 = (step * math.floor((float(v.min()) - 2) / step) for v in (col, row))
        c1, r1 = (step * math.ceil((float(v.max()) + 2) / step) for v in (col, row))
        out_shape = (max(2, round((r1 - r0) / decimate)), max(2, round((c1 - c0) / decimate)))
        if level is None:
            rgb = self.read_rgb(PixelWindow(c0, r0, c1 - c0, r1 - r0), out_shape=out_shape)
        else:
            rgb = self._level_crop(level, c0 // level, r0 // level, c1 // level, r1 // level, out_shape)
        scale = np.array([out_shape[1] / (c1 - c0), out_shape[0] / (r1 - r0)])
        homographies = []
        for grid_px, raster_px in zip(grids, pixels, strict=True):
            # Raster pixel coordinates put pixel centres at +0.5; OpenCV sampling puts them at integers.
            window_px = (raster_px - [c0, r0]) * scale - 0.5
            homographies.append(cv2.findHomography(grid_px, window_px, 0)[0])
        return rgb, homographies

    def _view_level(self, decimate: float) -> int | None:
        """The coarsest power-of-two level no coarser than ``decimate`` whose copy of the whole
        raster fits the view cache (None: none does, views are read from the file). A view is
        then a crop of memory instead of a decode of every file block under it: a correlation
        region at 1000 m covers most of a NAIP quarter quad, and a search reads dozens."""
        level = 1
        while 2 * level <= min(decimate, MAX_VIEW_LEVEL):
            level *= 2
        while level >= 1:
            if math.ceil(self.width / level) * math.ceil(self.height / level) * 3 <= self.view_cache_bytes:
                return level
            level //= 2
        return None

    def _level_crop(
        self, level: int, c0: int, r0: int, c1: int, r1: int, out_shape: tuple[int, int]
    ) -> np.ndarray:
        """Pixels [r0:r1, c0:c1] of the raster at ``level`` (0 off it), area-averaged to ``out_shape``."""
        image = self._levels.get(level)
        if image is None:
            rows, cols = math.ceil(self.height / level), math.ceil(self.width / level)
            image = self.read_rgb(PixelWindow(0, 0, cols * level, rows * level), out_shape=(rows, cols))
            self._levels[level] = image
        crop = np.zeros((r1 - r0, c1 - c0, 3), np.uint8)
        rows, cols = image.shape[:2]
        sr0, sc0, sr1, sc1 = max(r0, 0), max(c0, 0), min(r1, rows), min(c1, cols)
        if sr1 > sr0 and sc1 > sc0:
            crop[sr0 - r0 : sr1 - r0, sc0 - c0 : sc1 - c0] = image[sr0:sr1, sc0:sc1]
        if crop.shape[:2] == out_shape:
            return crop
        return cv2.resize(crop, (out_shape[1], out_shape[0]), interpolation=cv2.INTER_AREA)

    def water_mask(self, max_px: int = WATER_MASK_MAX_PX) -> tuple[np.ndarray, float] | None:
        """(mask, raster pixels per mask pixel): open water by the green and near-infrared bands'
        NDWI (McFeeters: water reflects green and absorbs near-infrared), read at most ``max_px``
        across. None where the raster has no near-infrared band (a fourth band that is not alpha,
        as NAIP's) or no water: colour alone does not tell a lake's dark green from a field's."""
        if self.band_count < 4 or self._ds.colorinterp[3] == ColorInterp.alpha:
            return None
        scale = max(1.0, max(self.width, self.height) / max_px)
        shape = (max(1, round(self.height / scale)), max(1, round(self.width / scale)))
        green, nir = (
            b.astype(np.float32)
            for b in self._ds.read([2, 4], out_shape=(2, *shape), resampling=Resampling.average)
        )
        water = (green - nir) > 0.0
        return (water, scale) if water.any() else None

    def read_view(self, out_to_latlon: PixelToLatLon, width: int, height: int, gsd_m: float) -> np.ndarray:
        """(height, width, 3) RGB view of the orthophoto through ``out_to_latlon``; 0 off the map."""
        return self.read_views([(out_to_latlon, width, height)], gsd_m)[0]

    def read_views(self, outputs: Sequence[tuple[PixelToLatLon, int, int]], gsd_m: float) -> list[np.ndarray]:
        """:meth:`read_view` of several outputs at one resolution, from one shared window."""
        rgb, homographies = self._read_shared_window(outputs, gsd_m)
        # Output pixel (i, j) samples its pixel centre (i + 0.5, j + 0.5).
        centres = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        return [
            cv2.warpPerspective(rgb, h @ centres, (width, height), flags=flags)
            for (_, width, height), h in zip(outputs, homographies, strict=True)
        ]

    def crop_to(self, bounds_crs: tuple[float, float, float, float], out: Path) -> Path:
        """Write the pixels covering ``(xmin, ymin, xmax, ymax)`` (this raster's CRS) as a GeoTIFF
        of their own, georeferencing, bands and nodata kept; written atomically."""
        xmin, ymin, xmax, ymax = bounds_crs
        exact = rasterio.windows.from_bounds(xmin, ymin, xmax, ymax, self.transform)
        col0, row0 = math.floor(exact.col_off + 1e-6), math.floor(exact.row_off + 1e-6)
        col1 = math.ceil(exact.col_off + exact.width - 1e-6)
        row1 = math.ceil(exact.row_off + exact.height - 1e-6)
        window = Window(col0, row0, col1 - col0, row1 - row0).intersection(
            Window(0, 0, self.width, self.height)
        )
        source = dict(self._ds.profile)
        # GDAL hands YCbCr-in-JPEG pixels over as RGB; written with another compression they are RGB.
        if str(source.get("photometric", "")).lower() == "ycbcr":
            source["photometric"] = "rgb"
        profile = {
            **source,
            "driver": "GTiff",
            "width": int(window.width),
            "height": int(window.height),
            "transform": self._ds.window_transform(window),
            "compress": "deflate",
        }
        return write_geotiff(out, self._ds.read(window=window), profile, self._ds.colorinterp)

    def check_readable(self, progress: Callable[[int, int], None] | None = None) -> None:
        """Read every block of the file once, so a truncated or damaged file is refused before
        work starts, naming the first block that cannot be read. ``progress(done, total)``."""
        blocks = list(self._ds.block_windows(1))
        for done, ((row, col), window) in enumerate(blocks, start=1):
            try:
                self._ds.read(window=window)
            except RasterioIOError as exc:
                span = (
                    f"rows {window.row_off}..{window.row_off + window.height}, "
                    f"columns {window.col_off}..{window.col_off + window.width}"
                )
                raise OrthonavError(
                    f"{self.path}: block {row},{col} ({span}) cannot be read ({exc}): "
                    "the file is truncated or damaged"
                ) from None
            if progress:
                progress(done, len(blocks))

    def close(self) -> None:
        self._ds.close()

    def __enter__(self) -> GeoRaster:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return (
            f"GeoRaster({self.path.name}, {self.width}x{self.height}, {self.band_count} bands "
            f"{self.dtype}, {self.crs.to_string()}, {self.gsd_m:.3f} m/px)"
        )


def bright_pixels(image: np.ndarray, above: int = 0) -> np.ndarray:
    """Where any band of an (H, W, C) image is brighter than ``above`` (off the map the readers
    and renderers return black): ``image.max(axis=2) > above``, band by band, as numpy reduces
    over the last axis of an interleaved image slowly (and a lost frame's search makes hundreds
    of views)."""
    brightest = image[..., 0]
    for band in range(1, image.shape[2]):
        brightest = np.maximum(brightest, image[..., band])
    return brightest > above


def write_geotiff(out: Path, data: np.ndarray, profile: dict, colorinterp: tuple | None = None) -> Path:
    """(bands, rows, cols) ``data`` as a GeoTIFF with ``profile``, written atomically."""
    with atomic_path(out) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        dst.write(data)
        if colorinterp is not None:
            dst.colorinterp = colorinterp
    return out


def _open_dataset(path: Path) -> rasterio.DatasetReader:
    if not path.exists():
        raise OrthonavError(f"{path}: no such file (expected a GeoTIFF orthophoto)")
    if path.is_dir():
        raise OrthonavError(f"{path}: is a directory (expected a GeoTIFF orthophoto file)")
    try:
        with warnings.catch_warnings():
            # A raster without georeferencing is refused below with a clearer message.
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            ds = rasterio.open(path)
    except RasterioIOError as exc:
        raise OrthonavError(f"{path}: not a readable GeoTIFF ({exc})") from None
    if ds.driver not in ("GTiff", "VRT"):  # a VRT: a mosaic of GeoTIFFs (orthonav.geo.mosaic)
        ds.close()
        raise OrthonavError(f"{path}: is a {ds.driver} raster, expected a GeoTIFF")
    if ds.crs is None:
        ds.close()
        raise OrthonavError(f"{path}: has no coordinate reference system (expected a georeferenced GeoTIFF)")
    if ds.count == 2 or ds.count < 1:
        ds.close()
        raise OrthonavError(f"{path}: has {ds.count} bands, expected 1 (gray), 3 (RGB) or 4")
    if ds.dtypes[0] not in SUPPORTED_DTYPES:
        ds.close()
        raise OrthonavError(f"{path}: pixel type {ds.dtypes[0]}, expected one of {SUPPORTED_DTYPES}")
    if ds.width < 16 or ds.height < 16:
        ds.close()
        raise OrthonavError(
            f"{path}: is only {ds.width}x{ds.height} px, too small for a map (expected at least 16x16 px)"
        )
    return ds


def _check_transform(path: Path, t: Affine) -> None:
    if t.b != 0.0 or t.d != 0.0:
        raise OrthonavError(
            f"{path}: has a rotated or sheared geotransform {tuple(t)[:6]}; expected north-up "
            "(warp it first, e.g. gdalwarp)"
        )
    if t.a <= 0.0 or t.e >= 0.0 or not (math.isfinite(t.a) and math.isfinite(t.e)):
        raise OrthonavError(
            f"{path}: degenerate or flipped geotransform (pixel size {t.a}, {t.e}); expected "
            "positive x size and negative y size (north-up)"
        )


def _check_coordinates(raster: GeoRaster) -> None:
    """Catch rasters whose coordinates cannot be in their CRS (e.g. WGS84 holding metres)."""
    path, crs = raster.path, raster.crs
    cols = np.array([0, raster.width, 0, raster.width, raster.width / 2])
    rows = np.array([0, 0, raster.height, raster.height, raster.height / 2])
    xs, ys = raster.pixel_to_crs(cols, rows)
    if crs.is_geographic and (np.abs(ys).max() > 90 or np.abs(xs).max() > 360):
        raise OrthonavError(
            f"{path}: claims geographic CRS {crs.to_string()} but its coordinates "
            f"({xs.min():.1f}..{xs.max():.1f}, {ys.min():.1f}..{ys.max():.1f}) are not degrees"
        )
    with np.errstate(all="ignore"):
        lat, lon = raster.pixel_to_latlon(cols, rows)
    if not (np.all(np.isfinite(lat)) and np.all(np.isfinite(lon))):
        raise OrthonavError(f"{path}: its corners cannot be converted from {crs.to_string()} to WGS84")
    area = crs.area_of_use
    if area is None and (code := crs.to_epsg()) is not None:
        # A CRS read from a GeoTIFF carries no area of use; the EPSG database knows it.
        area = CRS.from_epsg(code).area_of_use
    if area is not None:
        margin = 2.0
        lat_c, lon_c = float(lat[-1]), float(lon[-1])
        inside = area.south - margin <= lat_c <= area.north + margin and (
            area.west - margin <= lon_c <= area.east + margin or area.west > area.east
        )
        if not inside:
            raise OrthonavError(
                f"{path}: its centre ({lat_c:.4f}, {lon_c:.4f}) lies outside the area where "
                f"{crs.name} is valid ({area.west}..{area.east} E, {area.south}..{area.north} N): "
                "wrong CRS or wrong coordinates"
            )
    gsd = raster.gsd_m
    if not MIN_GSD_M <= gsd <= MAX_GSD_M:
        raise OrthonavError(
            f"{path}: pixel size {gsd:.6g} m on the ground is implausible for an orthophoto "
            f"(expected {MIN_GSD_M}..{MAX_GSD_M} m); wrong CRS or transform?"
        )


def _stretch_limits(raster: GeoRaster) -> tuple[float, float] | None:
    """Percentile stretch for non-uint8 data, from an overview; errors on empty imagery."""
    ds = raster._ds
    scale = max(raster.width, raster.height) / OVERVIEW_PX
    shape = (max(1, int(raster.height / max(scale, 1))), max(1, int(raster.width / max(scale, 1))))
    data = ds.read(1, out_shape=shape, masked=True, resampling=Resampling.nearest)
    valid = np.ma.compressed(data)
    valid = valid[np.isfinite(valid)] if valid.dtype.kind == "f" else valid
    if valid.size == 0 or np.all(valid == 0):
        raise OrthonavError(f"{raster.path}: the imagery is empty (all nodata or zero)")
    if valid.max() == valid.min():
        raise OrthonavError(
            f"{raster.path}: the imagery is a single constant value ({valid.min()}); nothing to match"
        )
    if raster.dtype == "uint8":
        return None
    lo, hi = np.percentile(valid, [1.0, 99.0])
    return float(lo), float(max(hi, lo + 1e-6))


def _to_uint8(data: np.ndarray, stretch: tuple[float, float] | None) -> np.ndarray:
    if stretch is None:
        return data.astype(np.uint8, copy=False)
    lo, hi = stretch
    scaled = (data.astype(np.float32) - lo) * (255.0 / (hi - lo))
    return np.clip(np.nan_to_num(scaled), 0, 255).astype(np.uint8)
