"""``orthonav demo``: terrain (or the user's GeoTIFF) -> map package -> one mission.

Everything is reused between runs when its inputs have not changed, so a second demo
only flies the mission.
"""

from __future__ import annotations

import json
import math
from contextlib import ExitStack
from pathlib import Path

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.localize import open_fix_source
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.sim.mission import SIMULATED_WORLD, MissionConfig, MissionResult, run_mission
from orthonav.sim.terrain import TerrainConfig, write_terrain_geotiff

DEMO_CAMERA = Camera.from_hfov(640, 480, 60.0)
DEMO_TERRAIN = TerrainConfig()
DEMO_ALT_M = 300.0


def demo_altitude(raster: GeoRaster, camera: Camera) -> float:
    """An altitude whose footprint spans about a fifth of the map's shorter side."""
    short_side_m = min(raster.width, raster.height) * raster.gsd_m
    width_per_alt = camera.width / camera.fx
    return float(max(20.0, min(3000.0, short_side_m / 5.0 / width_per_alt)))


def run_demo(
    out_dir: Path,
    map_tif: Path | None = None,
    frames_from: Path | None = None,
    altitude_m: float | None = None,
    seed: int = 0,
    progress: bool = True,
) -> MissionResult:
    """Fly the demo mission corner to corner; terrain and map are made once and reused."""
    out_dir.mkdir(parents=True, exist_ok=True)
    if map_tif is None:
        map_tif = out_dir / "terrain.tif"
        if not map_tif.exists():
            write_terrain_geotiff(map_tif, DEMO_TERRAIN)
        altitude_m = altitude_m or DEMO_ALT_M
    with GeoRaster(map_tif) as raster:
        altitude_m = altitude_m or demo_altitude(raster, DEMO_CAMERA)
    package = _map_package(map_tif, out_dir / "map", altitude_m, progress)
    start, target = _diagonal(package)
    config = MissionConfig(
        *start,
        *target,
        alt_agl_m=altitude_m,
        seed=seed,
        speed_mps=max(10.0, altitude_m / 15.0),
        arrival_radius_m=max(30.0, altitude_m / 5.0),
    )
    # The default fix source, as every command's: the cascade over the map's orthophoto.
    with ExitStack() as stack:
        frames = stack.enter_context(GeoRaster(frames_from or map_tif))
        source = open_fix_source(stack, package, DEMO_CAMERA, localizer=SIMULATED_WORLD).source
        return run_mission(
            package, frames, DEMO_CAMERA, config, out_dir / "run", progress=progress, fix_source=source
        )


def _map_package(map_tif: Path, map_dir: Path, altitude_m: float, progress: bool) -> MapPackage:
    """Reuse the map when it was built from the same file with the same altitude."""
    tiling = TilingConfig(nominal_alt_m=altitude_m)
    if (map_dir / "manifest.json").exists():
        try:
            package = MapPackage(map_dir)
            same = package.source_path == map_tif.resolve() and math.isclose(
                package.tiling.nominal_alt_m, altitude_m
            )
            if same:
                return package
        except (OrthonavError, KeyError, json.JSONDecodeError):
            pass
    return build_map(map_tif, map_dir, DEMO_CAMERA, tiling, overwrite=True, progress=progress)


def _diagonal(package: MapPackage) -> tuple[tuple[float, float], tuple[float, float]]:
    """Start and target at 15 % and 85 % along the map's diagonal."""
    w, h = package.grid.width, package.grid.height
    lat, lon = package.grid.pixel_to_latlon([0.15 * w, 0.85 * w], [0.15 * h, 0.85 * h])
    return (float(lat[0]), float(lon[0])), (float(lat[1]), float(lon[1]))
