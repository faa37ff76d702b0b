"""Geodesic distance/azimuth and local ENU frames, all through pyproj.

No hand-written lat/lon maths: distances and bearings use ``pyproj.Geod`` on WGS84, local
metric frames use an azimuthal equidistant projection centred on a reference point (true
metres on the ground near it, unlike UTM or Mercator grid units).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from pyproj import CRS, Geod, Transformer

from orthonav.errors import OrthonavError

WGS84 = CRS.from_epsg(4326)
GEOD = Geod(ellps="WGS84")


def check_latlon(lat: float, lon: float, field: str = "position") -> None:
    """Raise a clear error unless (lat, lon) is a finite WGS84 position."""
    if not (math.isfinite(lat) and math.isfinite(lon)):
        raise OrthonavError(f"{field}: latitude/longitude must be finite numbers, got {lat}, {lon}")
    if not -90.0 <= lat <= 90.0:
        raise OrthonavError(f"{field}: latitude {lat} is outside [-90, 90] degrees")
    if not -180.0 <= lon <= 180.0:
        raise OrthonavError(f"{field}: longitude {lon} is outside [-180, 180] degrees")


def distance_m(lat1, lon1, lat2, lon2) -> np.ndarray | float:
    """Geodesic distance in metres on WGS84 (scalars or arrays)."""
    _, _, dist = GEOD.inv(lon1, lat1, lon2, lat2)
    return dist


def azimuth_deg(lat1, lon1, lat2, lon2) -> np.ndarray | float:
    """Forward geodesic azimuth from point 1 to point 2, degrees clockwise from north in [0, 360)."""
    az, _, _ = GEOD.inv(lon1, lat1, lon2, lat2)
    az = np.mod(az, 360.0)
    return az - 360.0 * (az >= 360.0)  # np.mod(-1e-15, 360) rounds to 360.0


def destination(lat: float, lon: float, azimuth: float, dist_m: float) -> tuple[float, float]:
    """The point reached by flying ``dist_m`` metres from (lat, lon) on ``azimuth`` (deg)."""
    lon2, lat2, _ = GEOD.fwd(lon, lat, azimuth, dist_m)
    return float(lat2), float(lon2)


@lru_cache(maxsize=64)
def transformer(src: CRS | str, dst: CRS | str) -> Transformer:
    """A cached, always-xy (lon/lat, easting/northing order) transformer between two CRSs."""
    return Transformer.from_crs(src, dst, always_xy=True)


class LocalFrame:
    """East-North metres around a reference point (azimuthal equidistant projection).

    Used wherever a metric ground plane is needed: camera poses, homographies, covariances.
    """

    def __init__(self, lat0: float, lon0: float) -> None:
        check_latlon(lat0, lon0, "local frame origin")
        self.lat0 = float(lat0)
        self.lon0 = float(lon0)
        aeqd = f"+proj=aeqd +lat_0={self.lat0:.10f} +lon_0={self.lon0:.10f} +ellps=WGS84"
        # The operation PROJ itself picks between WGS84 and this projection, given as a
        # pipeline: Transformer.from_crs searches its database for it on every call, and every
        # correlation view builds several local frames; the pipeline needs no search and gives
        # the same numbers.
        pipeline = Transformer.from_pipeline(
            f"+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad +step {aeqd}"
        )
        self._from_wgs84 = pipeline
        self._to_wgs84 = _Inverse(pipeline)

    @staticmethod
    def around(lat: float, lon: float) -> LocalFrame:
        """A shared frame with its origin within ~8 km of (lat, lon): positions from several
        places in one frame.

        Scale error of the projection that far from its origin is below 1e-6.
        """
        return _cached_frame(round(float(lat), 1), round(float(lon), 1))

    @staticmethod
    def at(lat: float, lon: float) -> LocalFrame:
        """The frame with its origin at (lat, lon), shared by every call with that origin: a
        lost frame's search places its views around a few origins thousands of times (PROJ's
        pipeline built each time would be a large share of the search). Kept apart from :meth:`around`'s:
        every frame with a prior has an origin of its own, and would push those out."""
        return _exact_frame(float(lat), float(lon))

    def to_enu(self, lat, lon) -> tuple[np.ndarray, np.ndarray]:
        """WGS84 lat/lon -> (east_m, north_m)."""
        east, north = self._from_wgs84.transform(lon, lat)
        return np.asarray(east), np.asarray(north)

    def to_latlon(self, east, north) -> tuple[np.ndarray, np.ndarray]:
        """(east_m, north_m) -> WGS84 (lat, lon)."""
        lon, lat = self._to_wgs84.transform(east, north)
        return np.asarray(lat), np.asarray(lon)

    def from_crs(self, crs: CRS, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates in ``crs`` -> (east_m, north_m) in this frame.

        Always through WGS84 with the same transformer the rest of orthonav uses, so a datum
        shift (e.g. Bessel-based national grids) is applied identically in both directions.
        """
        lon, lat = transformer(crs, WGS84).transform(x, y)
        return self.to_enu(lat, lon)


class _Inverse:
    """A transformer run backwards, with the forward one's ``transform`` signature."""

    def __init__(self, forward: Transformer) -> None:
        self._forward = forward

    def transform(self, x, y):
        return self._forward.transform(x, y, direction="INVERSE")


@lru_cache(maxsize=256)
def _cached_frame(lat0: float, lon0: float) -> LocalFrame:
    return LocalFrame(lat0, lon0)


_exact_frame = lru_cache(maxsize=64)(LocalFrame)
