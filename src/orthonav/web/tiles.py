"""XYZ (Web Mercator) PNG tiles of an orthophoto in any CRS, rendered by rio-tiler.

rio-tiler reprojects and masks (nodata, alpha) itself; this module only picks the bands
(RGB, or the single gray band) and, for imagery deeper than 8 bits, the 2-98 % stretch
rio-tiler measures on the whole raster once.
"""

from __future__ import annotations

import math
import warnings
from functools import lru_cache
from pathlib import Path

from rasterio.crs import CRS
from rio_tiler.errors import NoOverviewWarning, TileOutsideBounds
from rio_tiler.io import Reader

from orthonav.web.store import NotFound


class TileTooCoarse(NotFound):
    """A zoom level the orthophoto cannot serve within a tile's time and memory budget."""


TILE_PX = 256
MAX_ZOOM = 24
STATS_PX = 512
# Source pixels a tile may read along its side (from the file or its best overview): bounds the
# time and memory of one request; a map zoomed further out than that is refused, not rendered.
MAX_READ_PX = 4096
EQUATOR_M = 40_075_016.686
WGS84 = CRS.from_epsg(4326)


# Small orthophotos have no overviews and need none; rio-tiler would warn on every tile.
warnings.filterwarnings("ignore", category=NoOverviewWarning)


def _indexes(reader: Reader) -> tuple[int, ...]:
    return (1, 2, 3) if reader.dataset.count >= 3 else (1,)


@lru_cache(maxsize=32)
def _stretch(path: Path, mtime: float) -> tuple[tuple[float, float], ...] | None:
    """Per-band (low, high) for non-8-bit imagery; ``mtime`` keys the cache to the file's version."""
    with Reader(path) as reader:
        if reader.dataset.dtypes[0] == "uint8":
            return None
        stats = reader.statistics(indexes=_indexes(reader), max_size=STATS_PX, percentiles=[2, 98])
    return tuple((s.percentile_2, s.percentile_98) for s in stats.values())


@lru_cache(maxsize=32)
def min_zoom(path: Path, mtime: float) -> int:
    """The lowest zoom whose tiles read at most ``MAX_READ_PX`` source pixels a side, given the
    orthophoto's resolution and overviews (``gdaladdo`` adds overviews and lowers it)."""
    with Reader(path) as reader:
        _, south, _, north = reader.get_geographic_bounds(WGS84)
        ds = reader.dataset
        factor = max([1, *ds.overviews(1)])
        if max(ds.width, ds.height) / factor <= MAX_READ_PX:
            return 0  # the whole orthophoto (or its smallest overview) is small enough to read
        unit_m = 1.0 if ds.crs.is_projected else EQUATOR_M / 360.0
        gsd_m = min(abs(ds.res[0]), abs(ds.res[1])) * unit_m * factor
    widest_lat = min(abs(south), abs(north)) if south * north > 0 else 0.0
    side_m = EQUATOR_M * math.cos(math.radians(widest_lat))
    return max(0, math.ceil(math.log2(side_m / (MAX_READ_PX * gsd_m))))


def render_tile(path: Path, z: int, x: int, y: int) -> bytes:
    """One 256 px PNG tile; tiles with no imagery raise ``NotFound``; a zoom too far out for the
    orthophoto (see :func:`min_zoom`) raises ``TileTooCoarse``."""
    lowest = min_zoom(path, path.stat().st_mtime)
    if z < lowest:
        raise TileTooCoarse(
            f"tile {z}/{x}/{y}: zoom {z} would read too much of {path.name} for one tile; "
            f"zoom in to {lowest} or more (or add overviews to the orthophoto: gdaladdo)"
        )
    stretch = _stretch(path, path.stat().st_mtime)
    with Reader(path) as reader:
        try:
            image = reader.tile(x, y, z, tilesize=TILE_PX, indexes=_indexes(reader))
        except TileOutsideBounds:
            raise NotFound(f"tile {z}/{x}/{y}: outside the orthophoto") from None
    if stretch is not None:
        image.rescale(in_range=stretch)
    return image.render(img_format="PNG")
