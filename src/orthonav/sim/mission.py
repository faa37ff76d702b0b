"""The navigation loop in simulation: INS + visual fixes + filter, from a start zone to a target.

The vehicle flies (``sim.kinematics``) at a constant speed, turning towards the target as
seen from its navigation estimate. An IMU with the configured errors drives a strapdown
INS (``fusion.InsSimulator``). While GNSS is available it aids the filter every second;
from ``gnss_loss_s`` on (0: lost from the start, where the vehicle knows
only that it is in the start zone) only the camera does. Every ``step_s`` a frame is
rendered at the TRUE pose (optionally from another orthophoto, e.g. another year) and
localized around the filter's estimate; the fix reaches the filter ``fix_latency_s`` later,
stamped with its capture time. The run ends when the estimate is within the arrival radius
of the target, at the time limit, when the vehicle leaves the map, or when the caller asks
it to stop (between frames).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO

import cv2
import numpy as np
from tqdm import tqdm

from orthonav.atomic import open_output, write_text_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError, require_positive
from orthonav.frames import MATCHES_PREFIX, Photometric, TruePose, render_frame
from orthonav.fusion import (
    FilterConfig,
    FixOutcome,
    ImuErrorModel,
    InsSample,
    InsSimulator,
    NavFilter,
    NavState,
)
from orthonav.fusion.consistency import consistency, consistency_line, nees
from orthonav.geo import GeoRaster, LocalFrame, azimuth_deg, check_latlon, destination, distance_m
from orthonav.localize import Localizer, LocalizerConfig, start_block
from orthonav.mapdb import MapPackage
from orthonav.sim.kinematics import Kinematics
from orthonav.types import Fix, FixSource, Pose, Prior
from orthonav.viz.matches import draw_matches
from orthonav.viz.mission import plot_mission

AHRS_SIGMA_DEG = 0.3
GNSS_PERIOD_S = 1.0
NAV_LOG_PERIOD_S = 1.0
NO_VISUAL = Fix(False, reason="visual fixes off (INS alone)")
MIN_PRIOR_SIGMA_M = 30.0  # below this the tile search would miss a fix the gate would accept
CANCELLED = "cancelled"  # the end reason of a run stopped by its ``should_stop``
INTERRUPTED = "interrupted"  # Ctrl-C: the step under way is dropped, the rest written as usual


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
    imu: str = "consumer"
    gnss_loss_s: float = 0.0
    gnss_sigma_m: float = 2.5
    ins_rate_hz: float = 10.0
    fix_latency_s: float = 0.5
    max_turn_rate_dps: float = 15.0
    visual_fixes: bool = True
    seed: int = 0
    save_frames: bool = False

    def __post_init__(self) -> None:
        check_latlon(self.start_lat, self.start_lon, "mission start")
        check_latlon(self.target_lat, self.target_lon, "mission target")
        require_positive(
            "mission",
            self,
            ("speed_mps", "step_s", "max_time_s", "arrival_radius_m", "ins_rate_hz", "gnss_sigma_m"),
        )
        for name in ("gnss_loss_s", "fix_latency_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise OrthonavError(f"mission {name}: expected seconds >= 0, got {value}")
        if self.fix_latency_s >= self.step_s:
            raise OrthonavError(
                f"mission fix_latency_s {self.fix_latency_s}: expected less than the frame step "
                f"{self.step_s} s"
            )
        if self.alt_agl_m is not None and not (math.isfinite(self.alt_agl_m) and self.alt_agl_m > 0):
            raise OrthonavError(f"mission alt_agl_m: expected a positive altitude, got {self.alt_agl_m}")
        ImuErrorModel.preset(self.imu)  # names the presets when the name is wrong


@dataclass
class MissionResult:
    """Summary of a finished run; the per-step and navigation logs are in the run directory."""

    run_dir: Path
    arrived: bool  # by the estimate: what the vehicle believed when it stopped
    end_reason: str
    steps: int
    flight_time_s: float
    true_distance_to_target_m: float
    arrival_radius_m: float
    fix_rate: float
    fused_rate: float
    errors_m: list[float] = field(default_factory=list)
    nav_errors_m: list[float] = field(default_factory=list)
    ins_error_end_m: float = 0.0
    step_ms: list[float] = field(default_factory=list)
    fixes_fused: int = 0
    consistency: dict = field(default_factory=dict)  # the filter's error against its sigma

    @property
    def arrived_true(self) -> bool:
        """Arrived by TRUE distance, not only by the estimate."""
        return self.true_distance_to_target_m <= self.arrival_radius_m

    @property
    def success(self) -> bool:
        """Arrived by the estimate and by truth, navigating on visual fixes: an INS that drifted
        onto the target by chance, or an estimate far from the truth, is no success."""
        return self.arrived and self.arrived_true and self.fixes_fused > 0

    @property
    def outcome(self) -> str:
        """One line that says whether the mission succeeded, and if not, why."""
        left = f"{self.true_distance_to_target_m:.0f} m from the target (radius {self.arrival_radius_m:g} m)"
        if self.success:
            verdict = f"arrived by estimate and by truth: {left}"
        elif self.arrived and self.arrived_true:
            verdict = f"arrived by estimate and by truth, but not on visual fixes: {left}"
        elif self.arrived:
            verdict = f"NOT arrived: the estimate says arrived but the vehicle is {left}"
        else:
            verdict = f"not arrived ({self.end_reason}): {left}"
        if self.fixes_fused == 0:
            verdict += f"; no visual fix fused in {self.steps} frames"
        return verdict

    def summary(self) -> dict:
        """The run's result as JSON: the verdict first, arrival by estimate and by truth side by side."""
        return {
            "outcome": self.outcome,
            "success": self.success,
            "arrived": self.arrived,
            "arrived_true": self.arrived_true,
            "true_distance_to_target_m": round(self.true_distance_to_target_m, 1),
            "arrival_radius_m": self.arrival_radius_m,
            "end_reason": self.end_reason,
            "steps": self.steps,
            "fixes_fused": self.fixes_fused,
            "flight_time_s": self.flight_time_s,
            "fix_rate": round(self.fix_rate, 3),
            "fused_rate": round(self.fused_rate, 3),
            **_stats("error", self.errors_m),
            **_stats("nav_error", self.nav_errors_m),
            **self.consistency,
            "ins_only_error_end_m": round(self.ins_error_end_m, 1),
            "step_ms_median": round(float(np.median(self.step_ms)), 1) if self.step_ms else None,
            "run_dir": str(self.run_dir),
        }


def _stats(name: str, values: list[float]) -> dict:
    err = np.asarray(values, float)
    stats = {"mean": np.mean, "median": np.median, "max": np.max}
    return {f"{name}_{k}_m": round(float(f(err)), 2) if len(err) else None for k, f in stats.items()}


class _Vehicle:
    """True motion plus the sensors a real vehicle has: IMU (through the INS), baro, AHRS, GNSS."""

    def __init__(self, config: MissionConfig, alt_m: float, rng: np.random.Generator) -> None:
        self.config, self.alt_m, self.rng = config, alt_m, rng
        offset_az, offset_r = rng.uniform(0, 360), config.start_zone_m * math.sqrt(rng.uniform())
        lat, lon = destination(config.start_lat, config.start_lon, offset_az, offset_r)
        heading = float(azimuth_deg(config.start_lat, config.start_lon, config.target_lat, config.target_lon))
        self.kin = Kinematics(lat, lon, heading, config.speed_mps, 0.0, config.max_turn_rate_dps)
        # With GNSS lost from the start the INS knows only the start zone's centre.
        ins_lat, ins_lon = (config.start_lat, config.start_lon) if config.gnss_loss_s == 0 else (lat, lon)
        self.ins = InsSimulator(
            ImuErrorModel.preset(config.imu), rng, 0.0, ins_lat, ins_lon, *self.kin.velocity_en_mps, heading
        )
        self.ins_sample = self.ins.sample

    def advance(self, dt_s: float, commanded_heading_deg: float) -> InsSample:
        motion = self.kin.advance(dt_s, commanded_heading_deg)
        self.ins_sample = self.ins.step(
            self.kin.time_s, motion.accel_east_mps2, motion.accel_north_mps2, motion.yaw_rate_dps, self.alt_m
        )
        return self.ins_sample

    def camera_pose(self) -> TruePose:
        """The camera at this instant: crab, altitude and attitude jitter around the flight path."""
        c, rng = self.config, self.rng
        return TruePose(
            self.kin.lat,
            self.kin.lon,
            self.alt_m * (1.0 + rng.uniform(-c.alt_jitter_m, c.alt_jitter_m)),
            (self.kin.heading_deg + rng.normal(0.0, c.heading_noise_deg)) % 360.0,
            float(rng.uniform(-1, 1) * c.attitude_jitter_deg),
            float(rng.uniform(-1, 1) * c.attitude_jitter_deg),
        )

    def ahrs(self, pose: TruePose) -> dict[str, float]:
        """Pitch and roll as the autopilot's attitude estimate reports them."""
        return {
            "pitch_deg": pose.pitch_deg + self.rng.normal(0.0, AHRS_SIGMA_DEG),
            "roll_deg": pose.roll_deg + self.rng.normal(0.0, AHRS_SIGMA_DEG),
        }

    def gnss_fix(self) -> Fix:
        """A GNSS position (no heading) as a ``Fix`` the filter fuses like any other."""
        sigma = self.config.gnss_sigma_m
        lat, lon = destination(
            self.kin.lat, self.kin.lon, self.rng.uniform(0, 360), abs(self.rng.normal(0.0, sigma * 1.2))
        )
        pose = Pose(lat, lon, self.alt_m, math.nan, 0.0, 0.0, lat, lon)
        return Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * sigma**2, method="gnss")


class _Run:
    """One mission's moving parts and its two logs (steps at frame rate, navigation at 1 Hz)."""

    def __init__(
        self,
        package: MapPackage,
        frames_from: GeoRaster,
        camera: Camera,
        config: MissionConfig,
        run_dir: Path,
        localizer: FixSource,
        map_orthophoto: GeoRaster | None = None,
    ) -> None:
        self.package, self.frames_from, self.camera, self.config = package, frames_from, camera, config
        self.run_dir, self.localizer = run_dir, localizer
        self.map_orthophoto = map_orthophoto  # to draw each fix's matches on (with save_frames)
        self.rng = np.random.default_rng(config.seed)
        self.vehicle = _Vehicle(config, config.alt_agl_m or package.tiling.nominal_alt_m, self.rng)
        self.nav = NavFilter(FilterConfig.for_imu(ImuErrorModel.preset(config.imu)))
        if config.gnss_loss_s == 0:
            self.nav.initialise(0.0, config.start_lat, config.start_lon, config.start_zone_m)
        else:
            fix = self.vehicle.gnss_fix()
            self.nav.initialise(0.0, fix.pose.lat, fix.pose.lon, config.gnss_sigma_m)
        self.nav.predict(self.vehicle.ins_sample)
        self.records: list[dict] = []
        self.nav_records: list[dict] = []

    @property
    def time_s(self) -> float:
        return self.vehicle.kin.time_s

    def fly_until(self, until_s: float, nav_log: IO[str]) -> None:
        """Advance vehicle, INS and filter tick by tick; GNSS aids while it lasts; log at 1 Hz."""
        tick = 1.0 / self.config.ins_rate_hz
        while self.time_s < until_s - 1e-9:
            state = self.nav.state()
            heading = float(azimuth_deg(state.lat, state.lon, self.config.target_lat, self.config.target_lon))
            before = self.time_s
            self.nav.predict(self.vehicle.advance(min(tick, until_s - self.time_s), heading))
            if self.time_s < self.config.gnss_loss_s and _crossed(before, self.time_s, GNSS_PERIOD_S):
                self.nav.update(self.vehicle.gnss_fix(), self.time_s)
            if _crossed(before, self.time_s, NAV_LOG_PERIOD_S):
                self._log_nav(nav_log)

    def _log_nav(self, nav_log: IO[str]) -> None:
        record = _nav_record(self.nav.state(), self.vehicle)
        self.nav_records.append(record)
        nav_log.write(json.dumps(record) + "\n")
        nav_log.flush()

    def frame_step(self, step: int, nav_log: IO[str]) -> dict:
        """Capture, localize around the estimate, fly through the latency, fuse at capture time."""
        started = time.perf_counter()
        capture_s = self.time_s
        pose = self.vehicle.camera_pose()
        prior, tiles = self._prior_and_candidates(pose, step)
        fix = self._localize(step, pose, prior, tiles) if self.config.visual_fixes else NO_VISUAL
        self.fly_until(capture_s + self.config.fix_latency_s, nav_log)
        outcome = self.nav.update(fix, capture_s)
        record = _step_record(step, capture_s, pose, fix, outcome, self.nav.state(), self.vehicle, tiles)
        record["step_ms"] = round(1000.0 * (time.perf_counter() - started), 1)
        self.records.append(record)
        return record

    def _localize(self, step: int, pose: TruePose, prior: Prior, tiles: np.ndarray | None) -> Fix:
        photometric = Photometric.random(self.rng, self.config.photometric_strength)
        frame = render_frame(self.frames_from, self.camera, pose, photometric, self.rng)
        if self.config.save_frames:
            cv2.imwrite(str(self.run_dir / "frames" / f"frame_{step:05d}.jpg"), frame)
        fix = self.localizer.localize(frame, prior, tiles)
        if self.map_orthophoto is not None and fix.inliers_map_px is not None and len(fix.inliers_map_px):
            picture = draw_matches(frame, fix, self.package, self.map_orthophoto)
            cv2.imwrite(str(self.run_dir / "frames" / f"{MATCHES_PREFIX}{step:05d}.jpg"), picture)
        return fix

    def _prior_and_candidates(self, pose: TruePose, step: int) -> tuple[Prior, np.ndarray | None]:
        """Search around the filter's estimate within its uncertainty; everywhere when it is lost.

        The first frame searches an m x m block of tiles around the start zone. Altitude (baro),
        heading and attitude (AHRS) are always known.
        """
        state = self.nav.state()
        attitude = self.vehicle.ahrs(pose)
        heading = state.heading_deg % 360.0
        c = self.config
        if step == 0 and c.gnss_loss_s == 0:
            centre, sigma = (c.start_lat, c.start_lon), max(c.start_zone_m, 50.0)
            tiles = start_block(self.package, c.start_lat, c.start_lon, c.start_block)
        elif state.status in ("lost", "uninitialised") or not self.package.grid.contains_latlon(
            state.lat, state.lon
        ):
            return Prior(alt_agl_m=pose.alt_agl_m, heading_deg=heading, **attitude), None
        else:
            centre, sigma, tiles = (state.lat, state.lon), max(MIN_PRIOR_SIGMA_M, 1.5 * state.sigma_m), None
        prior = Prior(
            *centre,
            pose.alt_agl_m,
            heading,
            sigma_m=sigma,
            heading_sigma_deg=max(state.heading_sigma_deg, 1.0),
            **attitude,
        )
        return prior, tiles


def _crossed(before_s: float, after_s: float, period_s: float) -> bool:
    """Whether a multiple of ``period_s`` lies in (before_s, after_s]."""
    return math.floor(after_s / period_s + 1e-9) > math.floor(before_s / period_s + 1e-9)


# Frames rendered from the orthophoto see a flat world: the localizer need not allow for a slope.
SIMULATED_WORLD = LocalizerConfig(flat_slope=0.0)


def run_mission(
    package: MapPackage,
    frames_from: GeoRaster,
    camera: Camera,
    config: MissionConfig,
    run_dir: Path,
    localizer_config: LocalizerConfig | None = None,
    progress: bool = True,
    fix_source: FixSource | None = None,
    should_stop: Callable[[], bool] | None = None,
) -> MissionResult:
    """Fly one mission and write its logs, summary and plot into ``run_dir``.

    Fixes come from the keypoint localizer over ``package`` (with ``localizer_config``; by
    default ``SIMULATED_WORLD``: the frames are rendered from the orthophoto, so the ground is
    exactly flat and no unseen slope is allowed for) unless another ``fix_source`` is given
    (e.g. the dense-correlation ``Corrector``, or the ``Cascade``: ``orthonav simulate`` gives it
    where the map's orthophoto is there). ``should_stop`` is asked before each frame; once
    it answers True the run ends, as ``CANCELLED``, with its outputs written. With
    ``save_frames`` each frame is saved, and beside it the picture of its fix's matches on the
    map's orthophoto when the fix source gives point matches.
    """
    for name, lat, lon in (
        ("start", config.start_lat, config.start_lon),
        ("target", config.target_lat, config.target_lon),
    ):
        if not package.grid.contains_latlon(lat, lon):
            raise OrthonavError(
                f"mission {name} {lat:.6f}, {lon:.6f} is outside the map {package.path}: it is "
                f"{package.away([lat], [lon])}"
            )
    run_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(
        run_dir / "config.json",
        json.dumps(
            {
                "mission": asdict(config),
                "map": str(package.path),
                "frames_from": str(frames_from.path),
                "camera": camera.to_dict(),
                "localizer": (localizer_config or SIMULATED_WORLD).to_dict(),
                "fix_source": getattr(fix_source, "method", "keypoints"),
            },
            indent=2,
        ),
    )
    if config.save_frames:
        (run_dir / "frames").mkdir(exist_ok=True)
    fix_source = fix_source or Localizer(package, camera, localizer_config or SIMULATED_WORLD)
    with _map_orthophoto(package, config) as map_orthophoto:
        run = _Run(package, frames_from, camera, config, run_dir, fix_source, map_orthophoto)
        end_reason = _fly(run, progress, should_stop or (lambda: False))
    return _finish(run, end_reason)


def _map_orthophoto(package: MapPackage, config: MissionConfig) -> GeoRaster | nullcontext[None]:
    """The map's own orthophoto, to draw matches on: only for saved frames, and if it is still there."""
    if config.save_frames and package.source_path.is_file():
        return GeoRaster(package.source_path)
    return nullcontext()


@contextmanager
def _logs(run_dir: Path) -> Iterator[tuple[IO[str], IO[str]]]:
    with open_output(run_dir / "steps.jsonl") as steps, open_output(run_dir / "nav.jsonl") as nav:
        yield steps, nav


def _fly(run: _Run, progress: bool, should_stop: Callable[[], bool]) -> str:
    """Frame after frame until arrival, the time limit, leaving the map, ``should_stop`` or
    Ctrl-C; logs flushed each step, so an interrupted run keeps every finished step."""
    try:
        return _fly_steps(run, progress, should_stop)
    except KeyboardInterrupt:
        return INTERRUPTED


def _fly_steps(run: _Run, progress: bool, should_stop: Callable[[], bool]) -> str:
    """The mission's frame steps; its bar is sized by the expected flight, not the time limit,
    and ends full with the reason the mission ended."""
    config = run.config
    max_steps = int(config.max_time_s // config.step_s)
    leg_m = distance_m(config.start_lat, config.start_lon, config.target_lat, config.target_lon)
    expected = min(max_steps, math.ceil(float(leg_m) / config.speed_mps / config.step_s) + 1)
    with (
        _logs(run.run_dir) as (step_log, nav_log),
        tqdm(total=expected, desc="mission", unit="step", disable=not progress) as bar,
    ):
        reason = _steps(run, max_steps, step_log, nav_log, bar, should_stop)
        bar.total = bar.n
        bar.set_postfix_str(reason)
    return reason


def _steps(run: _Run, max_steps: int, step_log, nav_log, bar: tqdm, should_stop: Callable[[], bool]) -> str:
    config = run.config
    run.fly_until(config.gnss_loss_s, nav_log)
    for step in range(max_steps):
        if should_stop():
            return CANCELLED
        record = run.frame_step(step, nav_log)
        step_log.write(json.dumps(record) + "\n")
        step_log.flush()
        bar.total = max(bar.total, step + 1)
        bar.update()
        state = run.nav.state()
        left = distance_m(state.lat, state.lon, config.target_lat, config.target_lon)
        if state.status in ("fixed", "dead reckoning") and left <= config.arrival_radius_m:
            return "arrived (by estimate)"
        run.fly_until((step + 1) * config.step_s + config.gnss_loss_s, nav_log)
        if not run.package.grid.contains_latlon(run.vehicle.kin.lat, run.vehicle.kin.lon):
            return "left the map"
    return "time limit"


def _nav_record(state: NavState, vehicle: _Vehicle) -> dict:
    """The filter's state beside the truth and the INS alone, at one instant."""
    kin, ins = vehicle.kin, vehicle.ins_sample
    return {
        "time_s": round(state.time_s, 3),
        "true_lat": kin.lat,
        "true_lon": kin.lon,
        "nav_lat": state.lat,
        "nav_lon": state.lon,
        "nav_error_m": float(distance_m(kin.lat, kin.lon, state.lat, state.lon)),
        "nav_sigma_m": round(state.sigma_m, 2),
        "nav_nees": _nees(state, kin.lat, kin.lon),
        "nav_status": state.status,
        "ins_lat": ins.lat,
        "ins_lon": ins.lon,
        "ins_error_m": float(distance_m(kin.lat, kin.lon, ins.lat, ins.lon)),
    }


def _nees(state: NavState, true_lat: float, true_lon: float) -> float | None:
    """The filter's NEES at this instant (:func:`orthonav.fusion.consistency.nees`)."""
    frame = LocalFrame.around(state.lat, state.lon)
    east, north = np.subtract(frame.to_enu(true_lat, true_lon), frame.to_enu(state.lat, state.lon))
    value = nees((float(east), float(north)), state.covariance_enu_m2)
    return None if value is None else round(value, 3)


def _step_record(
    step: int,
    capture_s: float,
    pose: TruePose,
    fix: Fix,
    outcome: FixOutcome,
    state: NavState,
    vehicle: _Vehicle,
    tiles: np.ndarray | None,
) -> dict:
    est = fix.pose if fix.accepted else None
    error = float(distance_m(pose.lat, pose.lon, est.lat, est.lon)) if est else None
    return {
        "step": step,
        "time_s": capture_s,
        "true_lat": pose.lat,
        "true_lon": pose.lon,
        "true_alt_m": pose.alt_agl_m,
        "true_heading_deg": pose.yaw_deg,
        "est_lat": est.lat if est else None,
        "est_lon": est.lon if est else None,
        "error_m": error,
        "accepted": fix.accepted,
        "reason": fix.reason,
        "fused": outcome.accepted,
        "filter": outcome.to_dict(),
        "candidate_tiles": None if tiles is None else len(tiles),
        "fix": fix.to_dict(),
        **_after_fusion(_nav_record(state, vehicle)),
    }


def _after_fusion(nav: dict) -> dict:
    """The filter's state once the fix was fused (``fix_latency_s`` after capture)."""
    return {
        "nav_time_s": nav["time_s"],
        **{k: v for k, v in nav.items() if k.startswith(("nav_", "ins_error"))},
    }


def _finish(run: _Run, end_reason: str) -> MissionResult:
    config, steps = run.config, run.records
    last_nav = run.nav_records[-1] if run.nav_records else _nav_record(run.nav.state(), run.vehicle)
    kin = run.vehicle.kin
    result = MissionResult(
        run_dir=run.run_dir,
        arrived=end_reason.startswith("arrived"),
        end_reason=end_reason,
        steps=len(steps),
        flight_time_s=round(run.time_s, 3),
        true_distance_to_target_m=float(distance_m(kin.lat, kin.lon, config.target_lat, config.target_lon)),
        arrival_radius_m=config.arrival_radius_m,
        fix_rate=sum(s["accepted"] for s in steps) / max(len(steps), 1),
        fused_rate=sum(s["fused"] for s in steps) / max(len(steps), 1),
        errors_m=[s["error_m"] for s in steps if s["error_m"] is not None],
        nav_errors_m=[r["nav_error_m"] for r in run.nav_records],
        ins_error_end_m=last_nav["ins_error_m"],
        step_ms=[s["step_ms"] for s in steps],
        fixes_fused=sum(s["fused"] for s in steps),
        consistency=consistency(
            [r["nav_error_m"] for r in run.nav_records],
            [r["nav_sigma_m"] for r in run.nav_records],
            [r["nav_nees"] for r in run.nav_records],
        ),
    )
    write_text_atomic(run.run_dir / "summary.json", json.dumps(result.summary(), indent=2))
    plot_mission(
        run.package,
        steps,
        run.nav_records,
        (config.start_lat, config.start_lon),
        (config.target_lat, config.target_lon),
        run.run_dir / "trajectory.png",
        config.arrival_radius_m,
        result.outcome,
        consistency_line(result.consistency),
    )
    return result
