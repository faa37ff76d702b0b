"""XYZ (Web Mercator) PNG tiles of an orthophoto in any CRS, rendered by rio-tiler, a few at a
time for the requests that want them.

rio-tiler reprojects and masks (nodata, alpha) itself; this module only picks the bands
(RGB, or the single gray band) and, for imagery deeper than 8 bits, the 2-98 % stretch
rio-tiler measures on the whole raster once. :class:`TileRenderer` bounds what tile requests
cost the server: a few render at once, each request waits a bounded time, and a request whose
client has left is not rendered.
"""

from __future__ import annotations

import asyncio
import math
import os
import threading
import warnings
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from pathlib import Path

from fastapi import HTTPException
from rasterio.crs import CRS
from rio_tiler.errors import NoOverviewWarning, TileOutsideBounds
from rio_tiler.io import Reader

from orthonav.web.store import NotFound
from orthonav.web.waiting import bounded_wait


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
CACHE_BYTES = 32 << 20  # rendered PNGs kept (about 200 tiles: a few screens of panning back)
RETRY_AFTER_S = 2
TileKey = tuple[Path, int, int, int, int]  # orthophoto, its mtime (ns), z, x, y


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
    orthophoto's resolution and overviews (``gdaladdo`` adds overviews and lowers it).

    However small the orthophoto, rio-tiler reprojects a tile's whole extent at the source's
    resolution: a world tile over a 1 km orthophoto still costs minutes and gigabytes."""
    with Reader(path) as reader:
        _, south, _, north = reader.get_geographic_bounds(WGS84)
        ds = reader.dataset
        factor = max([1, *ds.overviews(1)])
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


def default_tile_workers() -> int:
    """Tiles rendered at once: one per CPU core, at most 4 (each holds up to MAX_READ_PX^2 pixels
    a band in memory)."""
    return max(1, min(4, os.cpu_count() or 1))


class PngCache:
    """The most recently used tiles' PNG bytes, up to ``max_bytes`` in all (thread-safe: filled
    by the render threads, read by the event loop)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._tiles: OrderedDict[TileKey, bytes] = OrderedDict()
        self._size = 0
        self._lock = threading.Lock()

    def get(self, key: TileKey) -> bytes | None:
        with self._lock:
            png = self._tiles.get(key)
            if png is not None:
                self._tiles.move_to_end(key)
            return png

    def put(self, key: TileKey, png: bytes) -> None:
        with self._lock:
            if key in self._tiles or len(png) > self.max_bytes:
                return
            self._tiles[key] = png
            self._size += len(png)
            while self._size > self.max_bytes:
                self._size -= len(self._tiles.popitem(last=False)[1])


class TileRenderer:
    """Renders tiles for requests in ``workers`` threads, so that many requests at once (a page
    zoomed out over a large orthophoto) cost the memory of ``workers`` renders, not of all of
    them. A request waits for its tile at most ``timeout_s`` (then 503 with Retry-After; a render
    already started finishes into the cache, for the retry), and a request whose client has left
    while it waited, or that waits when the server stops, is dropped before its tile is rendered."""

    def __init__(
        self, workers: int, timeout_s: float, stopping: threading.Event, cache_bytes: int = CACHE_BYTES
    ) -> None:
        self.workers = workers
        self.timeout_s = timeout_s
        self.stopping = stopping
        self.cache = PngCache(cache_bytes)
        self._pool = ThreadPoolExecutor(workers, thread_name_prefix="orthonav-tiles")

    async def render(
        self, path: Path, z: int, x: int, y: int, client_left: Callable[[], Awaitable[bool]]
    ) -> bytes:
        """The tile's PNG; raises :class:`ClientLeft` when the client left before it was rendered."""
        key = (path, path.stat().st_mtime_ns, z, x, y)
        if (png := self.cache.get(key)) is not None:
            return png
        job = self._pool.submit(self._render, key)
        rendering = asyncio.wrap_future(job)
        try:
            return await bounded_wait(
                lambda: asyncio.shield(rendering), self.timeout_s, self.stopping, client_left
            )
        except TimeoutError:
            raise HTTPException(
                503,
                f"tile {z}/{x}/{y}: not rendered within {self.timeout_s:g} s, the server is busy "
                f"with other tiles ({self.workers} at a time); retry shortly",
                headers={"Retry-After": str(RETRY_AFTER_S)},
            ) from None
        finally:
            # Given up on, a tile not yet started is never rendered; one rendering ends in the cache.
            # The job itself is cancelled here: through ``rendering`` it would be on the loop's next
            # turn, after the answer may have gone out and a render thread may have taken it.
            job.cancel()
            rendering.cancel()

    def _render(self, key: TileKey) -> bytes:
        path, _, z, x, y = key
        png = render_tile(path, z, x, y)
        self.cache.put(key, png)
        return png

    def shutdown(self) -> None:
        """Drop the tiles still waiting; those rendering finish (each is bounded)."""
        self._pool.shutdown(wait=False, cancel_futures=True)
