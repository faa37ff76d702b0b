"""Feature-backend speed over frame sizes: extraction and frame-vs-tiles matching.

Each backend extracts a real-image frame of W x 3/4 W pixels and matches it against
``tiles`` real-image crops of W x W (a map tile at the frame's resolution), as one
localization step does. Medians of ``repeats`` runs after one warm-up; backends with a
learned matcher are also timed with their tiles in one padded batch, the alternative
to one pass per tile.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from orthonav.features import FeatureBackend, Runtime, backend_class, create_backend
from orthonav.geo import GeoRaster, PixelWindow

_BATCH = {None: "-", False: "per tile", True: "padded"}


def run_speed_table(
    image: Path,
    features: Sequence[str],
    sizes: Sequence[int] = (320, 640, 1024),
    tiles: int = 4,
    repeats: int = 5,
    runtime: Runtime | None = None,
    backend_conf: dict[str, dict] | None = None,
) -> list[dict]:
    """One row per backend, size and batching mode: median extract/match/total ms, keypoints."""
    runtime = runtime or Runtime()
    images = {size: _images(image, size, tiles) for size in sizes}
    rows = []
    for name in features:
        modes = (False, True) if backend_class(name).padded_batching else (None,)
        for padded in modes:
            backend = create_backend(
                name, replace(runtime, padded_batches=padded), **(backend_conf or {}).get(name, {})
            )
            for size in sizes:
                row = {"features": name, "size": f"{size}x{size * 3 // 4}", "batch": _BATCH[padded]}
                rows.append(row | _time_backend(backend, *images[size], repeats))
    return rows


def _images(path: Path, size: int, tiles: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """A frame-sized gray crop and ``tiles`` overlapping square crops around it."""
    with GeoRaster(path) as raster:
        side = min(raster.width, raster.height) / 2

        def read(col: float, row: float, w: int, h: int) -> np.ndarray:
            window = PixelWindow(col, row, side * w / size, side * h / size)
            return cv2.cvtColor(raster.read_rgb(window, out_shape=(h, w)), cv2.COLOR_RGB2GRAY)

        c0, r0 = raster.width / 4, raster.height / 4
        frame = read(c0 + side / 8, r0 + side / 8, size, size * 3 // 4)
        offsets = [(0, 0), (side / 4, 0), (0, side / 4), (side / 4, side / 4)]
        crops = [read(c0 + dx, r0 + dy, size, size) for dx, dy in (offsets * tiles)[:tiles]]
    return frame, crops


def _time_backend(backend: FeatureBackend, frame: np.ndarray, crops: list[np.ndarray], repeats: int) -> dict:
    tile_sets = [backend.extract(c) for c in crops]
    extract = _median_ms(lambda: backend.extract(frame), repeats)
    query = backend.extract(frame)
    match = _median_ms(lambda: backend.match_many(query, tile_sets), repeats)
    matches = backend.match_many(query, tile_sets)
    return {
        "keypoints": len(query),
        "matches": int(sum(len(m) for m in matches)),
        "extract_ms": round(extract, 1),
        "match_ms": round(match, 1),
        "total_ms": round(extract + match, 1),
    }


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    fn()  # warm-up: lazy allocations and kernel selection are not the steady state
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0)
    return float(np.median(times))
