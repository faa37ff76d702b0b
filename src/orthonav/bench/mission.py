"""``orthonav bench mission``: whole missions flown with INS + visual fixes + filter.

N missions per fix source over a real orthophoto map, frames rendered from another date,
GNSS lost from the start (the vehicle knows only its start zone), the INS drifting with the
chosen IMU. Fix sources: keypoint backends (the map package built with each) and
``correlation``, the dense gradient correlation against the orthophoto around the
filter's estimate. The same N start/target pairs and seeds are flown by every source and by
the INS alone (no visual fixes), side by side in one run. Arrival is judged by the TRUE
distance to the target when the estimate says it has arrived, not by the estimate alone.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.bench.scoring import mean, median, share
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import Runtime, available_backends
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize import CASCADE, CORRELATION, KEYPOINTS, make_fix_source, warm_up
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.sim import SIMULATED_WORLD, MissionConfig, MissionResult, run_mission
from orthonav.types import FixSource
from orthonav.viz.mission import plot_mission_bench

INS_ONLY = "ins-only"
# Fix sources that are not a keypoint backend's own map (correlation: the dense gradient one).
MAP_FREE = (CORRELATION, CASCADE)


@dataclass(frozen=True)
class MissionBenchConfig:
    """Everything that decides the numbers; written beside them."""

    missions: int = 30
    features: tuple[str, ...] = ("orb",)
    seed: int = 0
    width: int = 640
    height: int = 480
    hfov_deg: float = 60.0
    alt_m: float = 1000.0
    speed_mps: float = 20.0
    step_s: float = 5.0
    min_leg_m: float = 1500.0
    arrival_radius_m: float = 60.0
    start_zone_m: float = 100.0
    imu: str = "consumer"
    fix_latency_s: float = 0.5
    photometric: float = 0.6
    latency_s: float = 30.0

    def __post_init__(self) -> None:
        known = (*available_backends(), *MAP_FREE)
        unknown = set(self.features) - set(known)
        if unknown or not self.features:
            raise OrthonavError(f"bench features {sorted(unknown)}: expected names from {', '.join(known)}")
        if self.missions < 1:
            raise OrthonavError(f"bench missions: expected at least 1, got {self.missions}")

    @property
    def max_time_s(self) -> float:
        """Long enough for a detour of three times the longest possible leg."""
        return 3.0 * 1.5 * self.min_leg_m * 2.0 / self.speed_mps


def run_mission_benchmark(
    map_tif: Path,
    frames_tif: Path,
    out_json: Path,
    config: MissionBenchConfig = MissionBenchConfig(),
    progress: bool = True,
    runtime: Runtime | None = None,
) -> dict:
    """Fly every mission with every backend and with the INS alone; write JSON and a PNG."""
    watch = LoadWatch()
    camera = Camera.from_hfov(config.width, config.height, config.hfov_deg)
    runs_dir = out_json.with_suffix("")
    rows: list[dict] = []
    prepared: dict[str, tuple[MapPackage, FixSource | None]] = {}  # reused by the latency runs
    with (
        tempfile.TemporaryDirectory(prefix="orthonav-bench-mission-") as tmp,
        GeoRaster(frames_tif) as frames,
        GeoRaster(map_tif) as map_raster,
    ):
        for backend in (*config.features, INS_ONLY):
            package = _package(map_tif, Path(tmp), camera, backend, config, runtime)
            source = _fix_source(backend, package, map_raster, camera)
            prepared[backend] = package, source
            missions = _missions(package, camera, config)
            desc = f"bench mission {backend}"
            for i, mission in enumerate(tqdm(missions, desc=desc, disable=not progress)):
                if backend == INS_ONLY:
                    mission = replace(mission, visual_fixes=False)
                run_dir = runs_dir / backend / f"{i:03d}"
                result = run_mission(
                    package, frames, camera, mission, run_dir, progress=False, fix_source=source
                )
                rows.append({"features": backend, "mission": i, **_row(result)})
        latency = (
            [companion_latency(*prepared[b], map_raster, camera, b, config) for b in config.features]
            if config.latency_s
            else []
        )
    result = {
        "config": asdict(config),
        "map": str(map_tif),
        "frames_from": str(frames_tif),
        "rows": rows,
        "summary": _summary(rows),
        "latency": latency,
        "machine": watch.record((runtime or Runtime()).threads),
    }
    write_json_atomic(out_json, result)
    plot_mission_bench(rows, out_json.with_suffix(".png"))
    return result


def _package(
    map_tif: Path,
    tmp: Path,
    camera: Camera,
    backend: str,
    config: MissionBenchConfig,
    runtime: Runtime | None,
) -> MapPackage:
    """A keypoint backend's own map; correlation needs one only for its extent and the cascade
    for its fine stage: they use the first keypoint backend's (ORB's when there is none)."""
    keypoints = [f for f in config.features if f not in MAP_FREE]
    name = backend if backend in keypoints else (keypoints or ["orb"])[0]
    out = tmp / name
    if (out / "manifest.json").exists():
        return MapPackage(out)
    tiling = TilingConfig(nominal_alt_m=config.alt_m)
    return build_map(map_tif, out, camera, tiling, name, progress=False, runtime=runtime)


def _fix_source(backend: str, package: MapPackage, map_raster: GeoRaster, camera: Camera) -> FixSource | None:
    """Keypoints against the map package, dense correlation against the orthophoto, the cascade
    of both, or none."""
    if backend == INS_ONLY:
        return None
    name = backend if backend in MAP_FREE else KEYPOINTS
    return make_fix_source(name, package, camera, map_raster, SIMULATED_WORLD)


def companion_latency(
    package: MapPackage,
    source: FixSource,
    map_raster: GeoRaster,
    camera: Camera,
    backend: str,
    config: MissionBenchConfig,
    frames_from: GeoRaster | None = None,
) -> dict:
    """Companion mode against the simulated vehicle over UDP: frame capture -> MAVLink message.

    Frames come from ``frames_from`` (default: the map's own orthophoto, so that fixes are
    accepted and a latency exists for every backend; the accuracy across dates is what the
    missions measure). Another date's orthophoto gives the latency where frames are rejected
    and a chained fix source asks its later cascades.
    """
    from orthonav.mavlink.companion import CompanionConfig
    from orthonav.vehicle.loopback import fly_loopback
    from orthonav.vehicle.simulated import SimVehicleConfig

    mission = _missions(package, camera, replace(config, missions=1))[0]
    vehicle_config = SimVehicleConfig(
        mission.start_lat,
        mission.start_lon,
        mission.target_lat,
        mission.target_lon,
        speed_mps=config.speed_mps,
        alt_agl_m=config.alt_m,
        imu=config.imu,
        seed=config.seed,
    )
    warm_up(source, map_raster, camera, config.alt_m)  # as ``fly`` does before its first frame
    # The companion's events (no position before the first fix...) are in its log, not the table.
    with _quiet("orthonav.mavlink"):
        vehicle, companion = fly_loopback(
            source,
            frames_from or map_raster,
            camera,
            vehicle_config,
            # sim-vehicle reports its true attitude: a body camera's correlation fixes are fused
            CompanionConfig(duration_s=config.latency_s, independent_attitude=True),
            package.path.parent / f"loop_{backend}",
        )
    errors = vehicle.get("errors", {}).get("GPS_INPUT", {})
    keep = (
        "frames",
        "frames_dropped",
        "fused",
        "sent",
        "latency_median_ms",
        "latency_p95_ms",
        "wait_median_ms",  # of the latency, the fused fix's wait for its message
        "wait_p95_ms",
    )
    return {
        "features": backend,
        "seconds": config.latency_s,
        **{key: companion[key] for key in keep},
        "gps_input_error_median_m": errors.get("median_m"),
    }


@contextmanager
def _quiet(logger: str) -> Iterator[None]:
    log = logging.getLogger(logger)
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


def _missions(package: MapPackage, camera: Camera, config: MissionBenchConfig) -> list[MissionConfig]:
    """Seeded start/target pairs ``min_leg_m`` or more apart, a camera footprint inside the map."""
    rng = np.random.default_rng(config.seed)
    half_footprint_m = 0.5 * config.alt_m * camera.width / camera.fx
    margin = (half_footprint_m + config.start_zone_m) / package.gsd_m
    width, height = package.grid.width, package.grid.height
    if min(width, height) <= 2 * margin:
        raise OrthonavError(
            f"map {package.path}: {width}x{height} px is too small for missions at {config.alt_m:g} m "
            f"(a footprint plus the start zone needs {2 * margin:.0f} px each way)"
        )
    missions: list[MissionConfig] = []
    for _ in range(10_000):
        if len(missions) == config.missions:
            return missions
        cols, rows = rng.uniform(margin, width - margin, 2), rng.uniform(margin, height - margin, 2)
        lat, lon = package.grid.pixel_to_latlon(cols, rows)
        if distance_m(lat[0], lon[0], lat[1], lon[1]) < config.min_leg_m:
            continue
        missions.append(
            _mission(
                float(lat[0]), float(lon[0]), float(lat[1]), float(lon[1]), config, int(rng.integers(2**31))
            )
        )
    raise OrthonavError(
        f"map {package.path}: no start/target pairs {config.min_leg_m:g} m apart fit; lower --min-leg"
    )


def _mission(
    start_lat: float,
    start_lon: float,
    target_lat: float,
    target_lon: float,
    config: MissionBenchConfig,
    seed: int,
) -> MissionConfig:
    return MissionConfig(
        start_lat,
        start_lon,
        target_lat,
        target_lon,
        speed_mps=config.speed_mps,
        step_s=config.step_s,
        max_time_s=config.max_time_s,
        arrival_radius_m=config.arrival_radius_m,
        alt_agl_m=config.alt_m,
        start_zone_m=config.start_zone_m,
        photometric_strength=config.photometric,
        imu=config.imu,
        gnss_loss_s=0.0,
        fix_latency_s=config.fix_latency_s,
        seed=seed,
    )


def _row(result: MissionResult) -> dict:
    summary = result.summary()
    keep = (
        "arrived",
        "arrived_true",
        "end_reason",
        "steps",
        "flight_time_s",
        "true_distance_to_target_m",
        "fix_rate",
        "fused_rate",
        "nav_error_mean_m",
        "nav_error_max_m",
        "ins_only_error_end_m",
        "step_ms_median",
        "run_dir",
    )
    return {key: summary[key] for key in keep}


def _summary(rows: list[dict]) -> dict:
    """Per backend: arrival by estimate and by truth, errors, fix rate, time per step."""
    out: dict[str, dict] = {}
    for backend in dict.fromkeys(r["features"] for r in rows):
        group = [r for r in rows if r["features"] == backend]
        nav_mean = [r["nav_error_mean_m"] for r in group if r["nav_error_mean_m"] is not None]
        nav_max = [r["nav_error_max_m"] for r in group if r["nav_error_max_m"] is not None]
        out[backend] = {
            "missions": len(group),
            "arrived_by_estimate": share((r["arrived"] for r in group), len(group)),
            "arrived_true": share((r["arrived_true"] for r in group), len(group)),
            "true_distance_median_m": median(r["true_distance_to_target_m"] for r in group),
            "nav_error_mean_m": mean(nav_mean),
            # One lost mission dominates the mean over missions; the median says what is typical.
            "nav_error_median_m": median(nav_mean),
            "nav_error_max_m": round(float(np.max(nav_max)), 1) if nav_max else None,
            "fix_rate": mean((r["fix_rate"] for r in group), 3),
            "fused_rate": mean((r["fused_rate"] for r in group), 3),
            "step_ms_median": median(r["step_ms_median"] for r in group),
        }
    return out
