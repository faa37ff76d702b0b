"""``orthonav bench mapbuild``: map build throughput and peak memory by map size and worker count.

Maps are mosaics of the real NAIP years (:mod:`orthonav.bench.mosaic`), built with ORB at
the chosen altitude, single-process and on local Dask clusters, side by side. Each build runs
in a fresh process so that its peak memory (``ru_maxrss`` of the process and of its finished
children, the Dask workers) is its own. The imagery is 5 m/px: throughput is reported in
km^2/min at that resolution and as the same pixel rate over 0.5 m/px imagery.
"""

from __future__ import annotations

import multiprocessing
import resource
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.bench.mosaic import mosaic_layout, write_mosaic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.mapdb import TilingConfig, build_map
from orthonav.viz.mapbuild import plot_mapbuild_bench

REFERENCE_GSD_M = 0.5


@dataclass(frozen=True)
class MapBuildBenchConfig:
    """Everything that decides the numbers; written beside them."""

    blocks: tuple[int, ...] = (6, 24, 96, 192)  # beyond 40 blocks the mosaic repeats
    workers: tuple[int, ...] = (0, 1, 2)  # 0: the single-process build
    alt_m: float = 1000.0
    features: str = "orb"

    def __post_init__(self) -> None:
        if not self.blocks or min(self.blocks) < 1 or min(self.workers, default=-1) < 0:
            raise OrthonavError(f"bench mapbuild: expected blocks >= 1 and workers >= 0, got {self}")


def run_mapbuild_benchmark(sources: list[Path], out_json: Path, config: MapBuildBenchConfig) -> dict:
    watch = LoadWatch()
    rows = []
    with tempfile.TemporaryDirectory(prefix="orthonav-bench-mapbuild-") as tmp:
        for blocks in config.blocks:
            mosaic = mosaic_layout(sources, blocks, repeat=True)
            ortho = write_mosaic(mosaic, Path(tmp) / f"mosaic_{blocks}.tif")
            with GeoRaster(ortho) as raster:
                gsd_m = raster.gsd_m
            km2 = mosaic.area_km2(gsd_m)
            for workers in config.workers:
                out = Path(tmp) / f"map_{blocks}_{workers}"
                seconds, tiles, peak_mb = _build_in_fresh_process(ortho, out, config, workers)
                rows.append(_row(blocks, km2, gsd_m, workers, seconds, tiles, peak_mb))
    result = {
        "config": asdict(config),
        "sources": [str(p) for p in sources],
        "rows": rows,
        "machine": watch.record(),
    }
    write_json_atomic(out_json, result)
    plot_mapbuild_bench(rows, out_json.with_suffix(".png"))
    return result


def _row(
    blocks: int, km2: float, gsd_m: float, workers: int, seconds: float, tiles: int, peak_mb: float
) -> dict:
    per_min = km2 / seconds * 60.0
    return {
        "blocks": blocks,
        "km2": round(km2, 1),
        "workers": workers or "single",
        "tiles": tiles,
        "seconds": round(seconds, 2),
        "km2_per_min": round(per_min, 1),
        "km2_per_min_at_0.5m": round(per_min * (REFERENCE_GSD_M / gsd_m) ** 2, 2),
        "peak_mb": round(peak_mb),
    }


def _build_in_fresh_process(ortho: Path, out: Path, config: MapBuildBenchConfig, workers: int) -> tuple:
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_timed_build, ortho, out, config, workers).result()


def _timed_build(
    ortho: Path, out: Path, config: MapBuildBenchConfig, workers: int
) -> tuple[float, int, float]:
    """(seconds, tiles, peak resident MB of this process and its finished children)."""
    camera = Camera.from_hfov(640, 480, 60.0)
    started = time.perf_counter()
    package = build_map(
        ortho,
        out,
        camera,
        TilingConfig(nominal_alt_m=config.alt_m),
        config.features,
        progress=False,
        workers=workers or None,
    )
    seconds = time.perf_counter() - started
    peak_kb = max(
        resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
        resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss,
    )
    return seconds, len(package), peak_kb / 1024.0
