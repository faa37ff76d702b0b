"""Which map tiles to match a frame against.

Three cases: an m x m block around the start zone for the first frame;
after a fix, the tiles near points predicted along the main direction (towards the target)
and a few deviated directions; after a failed fix, every tile. A position prior with an
uncertainty gives a fourth, the tiles within a search radius.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from orthonav.geo import destination
from orthonav.mapdb import MapPackage


def all_tiles(package: MapPackage) -> np.ndarray:
    return np.arange(len(package))


def tiles_near(package: MapPackage, lat: float, lon: float, radius_m: float) -> np.ndarray:
    """Tiles within ``radius_m`` of a point, nearest first."""
    index = package.tiles_within(lat, lon, radius_m)
    centres = package.tiles.corners_latlon[index, 2]
    col, row = package.grid.latlon_to_pixel(lat, lon)
    ccol, crow = package.grid.latlon_to_pixel(centres[:, 0], centres[:, 1])
    return index[np.argsort(np.hypot(ccol - col, crow - row))]


def start_block(package: MapPackage, lat: float, lon: float, m: int = 3) -> np.ndarray:
    """The m x m block of tiles centred on the tile nearest the start point."""
    nearest = tiles_near(package, lat, lon, radius_m=package.gsd_m * package.grid.width * 2)[0]
    r0, c0 = package.tiles.grid_rc[nearest]
    rc = package.tiles.grid_rc
    half = m // 2
    inside = (np.abs(rc[:, 0] - r0) <= half) & (np.abs(rc[:, 1] - c0) <= half)
    return np.flatnonzero(inside)


def motion_prediction(
    package: MapPackage,
    lat: float,
    lon: float,
    bearing_deg: float,
    distance_m: float,
    radius_m: float,
    deviations_deg: Sequence[float] = (-30.0, -15.0, 0.0, 15.0, 30.0),
) -> np.ndarray:
    """Tiles near the points reachable by flying ``distance_m`` on the main bearing +- deviations."""
    found: list[np.ndarray] = [tiles_near(package, lat, lon, radius_m)]
    for deviation in deviations_deg:
        plat, plon = destination(lat, lon, bearing_deg + deviation, distance_m)
        found.append(tiles_near(package, plat, plon, radius_m))
    return np.unique(np.concatenate(found))
