"""The thesis's navigation loop in simulation: fly from a start zone to a target on fixes.

Each step renders the camera frame at the TRUE pose (optionally from another orthophoto,
e.g. another year), localizes it against the map, and steers: after a fix, towards the
target from the estimate; after a failed fix, on along the last bearing. The run stops
when the estimate is within the arrival radius of the target, or at the time limit.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from orthonav.atomic import write_text_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, azimuth_deg, check_latlon, destination, distance_m
from orthonav.localize import (
    Fix,
    Localizer,
    LocalizerConfig,
    Prior,
    all_tiles,
    motion_prediction,
    start_block,
)
from orthonav.mapdb import MapPackage
from orthonav.sim.render import Photometric, TruePose, render_frame
from orthonav.viz import plot_mission

AHRS_SIGMA_DEG = 0.3


@dataclass(frozen=True)
class MissionConfig:
    """A mission: where from, where to, how the vehicle flies and how its sensors err."""

    start_lat: float
    start_lon: float
    target_lat: float
    target_lon: float
    speed_mps: float = 20.0
    step_s: float = 5.0
    max_time_s: float = 1200.0
    arrival_radius_m: float = 60.0
    alt_agl_m: float | None = None
    alt_jitter_m: float = 0.05
    attitude_jitter_deg: float = 3.0
    heading_noise_deg: float = 3.0
    start_zone_m: float = 100.0
    start_block: int = 3
    photometric_strength: float = 0.6
    seed: int = 0
    save_frames: bool = False

    def __post_init__(self) -> None:
        check_latlon(self.start_lat, self.start_lon, "mission start")
        check_latlon(self.target_lat, self.target_lon, "mission target")
        for name in ("speed_mps", "step_s", "max_time_s", "arrival_radius_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise OrthonavError(f"mission {name}: expected a positive number, got {value}")
        if self.alt_agl_m is not None and not (math.isfinite(self.alt_agl_m) and self.alt_agl_m > 0):
            raise OrthonavError(f"mission alt_agl_m: expected a positive altitude, got {self.alt_agl_m}")


@dataclass
class MissionResult:
    """Summary of a finished run; the per-step log is in the run directory."""

    run_dir: Path
    arrived: bool
    end_reason: str
    steps: int
    flight_time_s: float
    true_distance_to_target_m: float
    fix_rate: float
    errors_m: list[float] = field(default_factory=list)

    def summary(self) -> dict:
        err = np.asarray(self.errors_m, float)
        stats = {"mean": np.mean, "median": np.median, "max": np.max}
        return {
            "arrived": self.arrived,
            "end_reason": self.end_reason,
            "steps": self.steps,
            "flight_time_s": self.flight_time_s,
            "true_distance_to_target_m": round(self.true_distance_to_target_m, 1),
            "fix_rate": round(self.fix_rate, 3),
            **{f"error_{k}_m": round(float(f(err)), 2) if len(err) else None for k, f in stats.items()},
            "run_dir": str(self.run_dir),
        }


class _Vehicle:
    """True state plus the noisy sensors a real vehicle would have (compass, baro, AHRS)."""

    def __init__(self, config: MissionConfig, alt_m: float, rng: np.random.Generator) -> None:
        self.config, self.alt_m, self.rng = config, alt_m, rng
        offset_az, offset_r = rng.uniform(0, 360), config.start_zone_m * math.sqrt(rng.uniform())
        self.lat, self.lon = destination(config.start_lat, config.start_lon, offset_az, offset_r)

    def true_pose(self, heading_deg: float) -> TruePose:
        c, rng = self.config, self.rng
        return TruePose(
            self.lat,
            self.lon,
            self.alt_m * (1.0 + rng.uniform(-c.alt_jitter_m, c.alt_jitter_m)),
            (heading_deg + rng.normal(0.0, c.heading_noise_deg)) % 360.0,
            float(rng.uniform(-1, 1) * c.attitude_jitter_deg),
            float(rng.uniform(-1, 1) * c.attitude_jitter_deg),
        )

    def ahrs(self, pose: TruePose) -> dict[str, float]:
        """Pitch and roll as the autopilot's attitude estimate reports them."""
        return {
            "pitch_deg": pose.pitch_deg + self.rng.normal(0.0, AHRS_SIGMA_DEG),
            "roll_deg": pose.roll_deg + self.rng.normal(0.0, AHRS_SIGMA_DEG),
        }

    def fly(self, pose: TruePose) -> None:
        self.lat, self.lon = destination(
            self.lat, self.lon, pose.yaw_deg, self.config.speed_mps * self.config.step_s
        )


def run_mission(
    package: MapPackage,
    frames_from: GeoRaster,
    camera: Camera,
    config: MissionConfig,
    run_dir: Path,
    localizer_config: LocalizerConfig | None = None,
    progress: bool = True,
) -> MissionResult:
    """Fly one mission and write its log, summary and plot into ``run_dir``."""
    for name, lat, lon in (
        ("start", config.start_lat, config.start_lon),
        ("target", config.target_lat, config.target_lon),
    ):
        if not package.grid.contains_latlon(lat, lon):
            raise OrthonavError(f"mission {name} {lat:.6f}, {lon:.6f} is outside the map {package.path}")
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(
        json.dumps(
            {
                "mission": asdict(config),
                "map": str(package.path),
                "frames_from": str(frames_from.path),
                "camera": camera.to_dict(),
                "localizer": (localizer_config or LocalizerConfig()).to_dict(),
            },
            indent=2,
        )
    )
    if config.save_frames:
        (run_dir / "frames").mkdir(exist_ok=True)
    rng = np.random.default_rng(config.seed)
    localizer = Localizer(package, camera, localizer_config)
    vehicle = _Vehicle(config, config.alt_agl_m or package.tiling.nominal_alt_m, rng)
    steps, end_reason = _fly(package, frames_from, camera, config, run_dir, rng, localizer, vehicle, progress)
    return _finish(run_dir, config, steps, end_reason, package)


def _fly(
    package: MapPackage,
    frames_from: GeoRaster,
    camera: Camera,
    config: MissionConfig,
    run_dir: Path,
    rng: np.random.Generator,
    localizer: Localizer,
    vehicle: _Vehicle,
    progress: bool,
) -> tuple[list[dict], str]:
    """Step until arrival, the time limit or leaving the map; the log is flushed every step."""
    estimate: tuple[float, float] | None = None
    since_fix_s = 0.0
    bearing = float(azimuth_deg(config.start_lat, config.start_lon, config.target_lat, config.target_lon))
    records: list[dict] = []
    max_steps = int(config.max_time_s // config.step_s)
    log_path = run_dir / "steps.jsonl"
    with (
        open(log_path, "w") as log,
        tqdm(total=max_steps, desc="mission", unit="step", disable=not progress) as bar,
    ):
        for step in range(max_steps):
            pose = vehicle.true_pose(bearing)
            frame = render_frame(
                frames_from, camera, pose, Photometric.random(rng, config.photometric_strength), rng
            )
            prior, tiles = _prior_and_candidates(
                package, config, pose, vehicle.ahrs(pose), estimate, bearing, since_fix_s, step
            )
            fix = localizer.localize(frame, prior, tiles)
            if config.save_frames:
                cv2.imwrite(str(run_dir / "frames" / f"frame_{step:05d}.jpg"), frame)
            record = _record(step, config, pose, fix, len(tiles))
            records.append(record)
            log.write(json.dumps(record) + "\n")
            log.flush()
            bar.update()
            if fix.accepted:
                estimate = (fix.pose.lat, fix.pose.lon)
                since_fix_s = 0.0
                bearing = float(azimuth_deg(*estimate, config.target_lat, config.target_lon))
                if distance_m(*estimate, config.target_lat, config.target_lon) <= config.arrival_radius_m:
                    return records, "arrived (by estimate)"
            vehicle.fly(pose)
            since_fix_s += config.step_s
            if not package.grid.contains_latlon(vehicle.lat, vehicle.lon):
                return records, "left the map"
    return records, "time limit"


def _prior_and_candidates(
    package: MapPackage,
    config: MissionConfig,
    pose: TruePose,
    attitude: dict[str, float],
    estimate: tuple[float, float] | None,
    bearing: float,
    since_fix_s: float,
    step: int,
) -> tuple[Prior, np.ndarray]:
    """The thesis's candidate tiles: start block, motion prediction after a fix, all after a miss.

    Altitude (barometer), heading (compass) and attitude (AHRS) are always known.
    """
    if step == 0:
        prior = Prior(
            config.start_lat,
            config.start_lon,
            pose.alt_agl_m,
            bearing,
            sigma_m=max(config.start_zone_m, 50.0),
            **attitude,
        )
        return prior, start_block(package, config.start_lat, config.start_lon, config.start_block)
    if estimate is None or since_fix_s > config.step_s:
        return Prior(alt_agl_m=pose.alt_agl_m, heading_deg=bearing, **attitude), all_tiles(package)
    travelled = config.speed_mps * since_fix_s
    predicted = destination(*estimate, bearing, travelled)
    sigma = 30.0 + 0.2 * travelled
    tiles = motion_prediction(package, *estimate, bearing, travelled, radius_m=2.0 * sigma)
    return Prior(*predicted, pose.alt_agl_m, bearing, sigma_m=sigma, **attitude), tiles


def _record(step: int, config: MissionConfig, pose: TruePose, fix: Fix, n_tiles: int) -> dict:
    est = fix.pose if fix.accepted else None
    error = float(distance_m(pose.lat, pose.lon, est.lat, est.lon)) if est else None
    return {
        "step": step,
        "time_s": step * config.step_s,
        "true_lat": pose.lat,
        "true_lon": pose.lon,
        "true_alt_m": pose.alt_agl_m,
        "true_heading_deg": pose.yaw_deg,
        "est_lat": est.lat if est else None,
        "est_lon": est.lon if est else None,
        "error_m": error,
        "accepted": fix.accepted,
        "reason": fix.reason,
        "candidate_tiles": n_tiles,
        "fix": fix.to_dict(),
    }


def _finish(
    run_dir: Path, config: MissionConfig, steps: list[dict], end_reason: str, package: MapPackage
) -> MissionResult:
    last = steps[-1]
    result = MissionResult(
        run_dir=run_dir,
        arrived=end_reason.startswith("arrived"),
        end_reason=end_reason,
        steps=len(steps),
        flight_time_s=len(steps) * config.step_s,
        true_distance_to_target_m=float(
            distance_m(last["true_lat"], last["true_lon"], config.target_lat, config.target_lon)
        ),
        fix_rate=sum(s["accepted"] for s in steps) / len(steps),
        errors_m=[s["error_m"] for s in steps if s["error_m"] is not None],
    )
    write_text_atomic(run_dir / "summary.json", json.dumps(result.summary(), indent=2))
    plot_mission(
        package,
        steps,
        (config.start_lat, config.start_lon),
        (config.target_lat, config.target_lon),
        run_dir / "trajectory.png",
    )
    return result
