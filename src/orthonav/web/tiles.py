"""XYZ (Web Mercator) PNG tiles of an orthophoto in any CRS, rendered by rio-tiler.

rio-tiler reprojects and masks (nodata, alpha) itself; this module only picks the bands
(RGB, or the single gray band) and, for imagery deeper than 8 bits, the 2-98 % stretch
rio-tiler measures on the whole raster once.
"""

from __future__ import annotations

import warnings
from functools import lru_cache
from pathlib import Path

from rio_tiler.errors import NoOverviewWarning, TileOutsideBounds
from rio_tiler.io import Reader

from orthonav.web.store import NotFound

TILE_PX = 256
MAX_ZOOM = 24
STATS_PX = 512


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


def render_tile(path: Path, z: int, x: int, y: int) -> bytes:
    """One 256 px PNG tile; tiles with no imagery raise ``NotFound``."""
    stretch = _stretch(path, path.stat().st_mtime)
    with Reader(path) as reader:
        try:
            image = reader.tile(x, y, z, tilesize=TILE_PX, indexes=_indexes(reader))
        except TileOutsideBounds:
            raise NotFound(f"tile {z}/{x}/{y}: outside the orthophoto") from None
    if stretch is not None:
        image.rescale(in_range=stretch)
    return image.render(img_format="PNG")
