"""A north-up pixel grid in a CRS: pixel <-> CRS <-> WGS84 and ground sample distance.

Pixel coordinates are (col, row) with the origin at the top-left corner of the top-left
pixel (rasterio's convention): the centre of pixel (0, 0) is (0.5, 0.5).
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
from affine import Affine
from pyproj import CRS, Transformer

from orthonav.geo.geodesy import WGS84, distance_m, transformer


class GeoGrid:
    """Raster geometry without pixels: a CRS, an affine transform and a size."""

    def __init__(self, crs: CRS, transform: Affine, width: int, height: int) -> None:
        self.crs = crs
        self.transform = transform
        self.width = int(width)
        self.height = int(height)

    def scaled(self, factor: float) -> GeoGrid:
        """The same area with pixels ``factor`` times larger (factor > 1 = coarser)."""
        return GeoGrid(
            self.crs,
            self.transform @ Affine.scale(factor),
            max(1, round(self.width / factor)),
            max(1, round(self.height / factor)),
        )

    # The grid's own transformers: looking them up in the shared cache hashes the CRS (its WKT),
    # a cost a correlation search paid thousands of times.
    @cached_property
    def _to_wgs84(self) -> Transformer:
        return transformer(self.crs, WGS84)

    @cached_property
    def _from_wgs84(self) -> Transformer:
        return transformer(WGS84, self.crs)

    def pixel_to_crs(self, cols, rows) -> tuple[np.ndarray, np.ndarray]:
        """Pixel (col, row) -> map CRS (x, y)."""
        t = self.transform
        cols, rows = np.asarray(cols, float), np.asarray(rows, float)
        return t.a * cols + t.b * rows + t.c, t.d * cols + t.e * rows + t.f

    def crs_to_pixel(self, xs, ys) -> tuple[np.ndarray, np.ndarray]:
        """Map CRS (x, y) -> pixel (col, row)."""
        inv = ~self.transform
        xs, ys = np.asarray(xs, float), np.asarray(ys, float)
        return inv.a * xs + inv.b * ys + inv.c, inv.d * xs + inv.e * ys + inv.f

    def pixel_to_latlon(self, cols, rows) -> tuple[np.ndarray, np.ndarray]:
        """Pixel (col, row) -> WGS84 (lat, lon)."""
        xs, ys = self.pixel_to_crs(cols, rows)
        lon, lat = self._to_wgs84.transform(xs, ys)
        return np.asarray(lat), np.asarray(lon)

    def latlon_to_pixel(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:
        """WGS84 (lat, lon) -> pixel (col, row)."""
        xs, ys = self._from_wgs84.transform(lon, lat)
        return self.crs_to_pixel(xs, ys)

    def contains_latlon(self, lat: float, lon: float, margin_px: float = 0.0) -> bool:
        """Whether a WGS84 point lies on the raster (optionally with a margin in pixels)."""
        col, row = self.latlon_to_pixel(lat, lon)
        return bool(
            -margin_px <= col <= self.width + margin_px and -margin_px <= row <= self.height + margin_px
        )

    @property
    def gsd_m(self) -> float:
        """Ground sample distance in true metres at the raster centre (mean of x and y)."""
        return float(np.mean(self.gsd_xy_m))

    @property
    def gsd_xy_m(self) -> tuple[float, float]:
        """Ground size of one pixel (x, y) in true metres at the raster centre."""
        c, r = self.width / 2.0, self.height / 2.0
        lat, lon = self.pixel_to_latlon([c, c + 1, c], [r, r, r + 1])
        gx = distance_m(lat[0], lon[0], lat[1], lon[1])
        gy = distance_m(lat[0], lon[0], lat[2], lon[2])
        return float(gx), float(gy)

    @property
    def center_latlon(self) -> tuple[float, float]:
        lat, lon = self.pixel_to_latlon(self.width / 2.0, self.height / 2.0)
        return float(lat), float(lon)

    def bounds_latlon(self) -> list[list[float]]:
        """[[south, west], [north, east]] (deg) of the grid's four corners, as Leaflet takes them."""
        lat, lon = self.pixel_to_latlon([0, self.width, 0, self.width], [0, 0, self.height, self.height])
        return [[float(lat.min()), float(lon.min())], [float(lat.max()), float(lon.max())]]
