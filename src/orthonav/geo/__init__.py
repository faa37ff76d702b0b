"""Geography: GeoTIFF orthophotos, pixel <-> CRS <-> WGS84, geodesics and local ENU frames."""

from orthonav.geo.geodesy import (
    GEOD,
    WGS84,
    LocalFrame,
    azimuth_deg,
    check_latlon,
    destination,
    distance_m,
    transformer,
)
from orthonav.geo.grid import GeoGrid
from orthonav.geo.raster import GeoRaster, PixelWindow, bounded_block_cache, bright_pixels, write_geotiff

__all__ = [
    "GEOD",
    "WGS84",
    "GeoGrid",
    "GeoRaster",
    "LocalFrame",
    "PixelWindow",
    "azimuth_deg",
    "bounded_block_cache",
    "bright_pixels",
    "check_latlon",
    "destination",
    "distance_m",
    "transformer",
    "write_geotiff",
]
