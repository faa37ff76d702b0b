"""A simulated vehicle that speaks MAVLink like an ArduPilot copter, for closing the loop on one machine.

It flies from a start to a target at real time (``sim.kinematics``), steering on what its
autopilot believes: the truth while GNSS works, its INS (``fusion.InsSimulator``, drifting)
after ``gnss_loss_s``. It streams what an autopilot streams (HEARTBEAT, SYSTEM_TIME and
GPS_GLOBAL_ORIGIN at 1 Hz; ATTITUDE, GLOBAL_POSITION_INT, LOCAL_POSITION_NED, VFR_HUD at the
telemetry rate), all from that belief, renders camera frames at the TRUE pose from another
orthophoto into a folder (``frames.frame_filename(capture time)``, written atomically) and/or
serves them as a live MJPEG-over-HTTP stream (``frames.mjpeg``, like an IP camera), and
grades what it is sent: each GPS_INPUT, VISION_POSITION_ESTIMATE, ODOMETRY or
GLOBAL_POSITION_SENSOR is logged to ``received.jsonl`` with its error against the true position
at its capture time; a ``summary.json`` is written when the run ends. The autopilot's EKF
origin (= home) is the start.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import Counter, deque
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from orthonav.atomic import atomic_path, open_output, write_json_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError, require_positive
from orthonav.frames import MjpegServer, frame_filename
from orthonav.frames.render import Photometric, TruePose, render_frame
from orthonav.fusion import ImuErrorModel, InsSample, InsSimulator
from orthonav.geo import GeoRaster, LocalFrame, azimuth_deg, check_latlon, distance_m
from orthonav.mavlink.link import MavLink, dialect
from orthonav.sim.kinematics import Kinematics, Motion

log = logging.getLogger(__name__)

GRAVITY_MPS2 = 9.80665
POSITION_TYPES = ("GPS_INPUT", "VISION_POSITION_ESTIMATE", "ODOMETRY", "GLOBAL_POSITION_SENSOR")
UNIX_USEC_MIN = 10**15  # smaller MAVLink timestamps are microseconds since boot
LOCAL_FRAMES = (1, 20)  # MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD: NED axes at the origin


@dataclass(frozen=True)
class SimVehicleConfig:
    """The flight, the sensors and the streaming rates of a simulated vehicle."""

    start_lat: float
    start_lon: float
    target_lat: float
    target_lon: float
    speed_mps: float = 15.0
    alt_agl_m: float = 300.0
    ground_alt_msl_m: float = 100.0
    gnss_loss_s: float = 0.0
    imu: str = "consumer"
    max_turn_rate_dps: float = 15.0
    physics_rate_hz: float = 20.0
    telemetry_rate_hz: float = 10.0
    frame_rate_hz: float = 2.0
    photometric_strength: float = 0.3
    truth_history_s: float = 60.0
    seed: int = 0

    def __post_init__(self) -> None:
        check_latlon(self.start_lat, self.start_lon, "sim vehicle start")
        check_latlon(self.target_lat, self.target_lon, "sim vehicle target")
        require_positive(
            "sim vehicle",
            self,
            (
                "speed_mps",
                "alt_agl_m",
                "physics_rate_hz",
                "telemetry_rate_hz",
                "frame_rate_hz",
                "truth_history_s",
            ),
        )
        if not (math.isfinite(self.gnss_loss_s) and self.gnss_loss_s >= 0):
            raise OrthonavError(f"sim vehicle gnss_loss_s: expected seconds >= 0, got {self.gnss_loss_s}")
        ImuErrorModel.preset(self.imu)


class _Every:
    """Due once per period; late calls do not pile up."""

    def __init__(self, rate_hz: float, start_s: float) -> None:
        self.period_s, self.next_s = 1.0 / rate_hz, start_s

    def due(self, now_s: float) -> bool:
        if now_s < self.next_s:
            return False
        self.next_s = max(self.next_s + self.period_s, now_s)
        return True


class _Truth:
    """Recent true positions (ENU metres around the origin) to grade messages at their capture time."""

    def __init__(self, frame: LocalFrame, history_s: float) -> None:
        self.frame, self.history_s = frame, history_s
        self._rows: deque[tuple[float, float, float]] = deque()

    def add(self, time_s: float, lat: float, lon: float) -> None:
        east, north = self.frame.to_enu(lat, lon)
        self._rows.append((time_s, float(east), float(north)))
        while self._rows and self._rows[0][0] < time_s - self.history_s:
            self._rows.popleft()

    def at(self, time_s: float) -> tuple[float, float] | None:
        """(east, north) at ``time_s``, or None outside the kept history."""
        if not self._rows or not self._rows[0][0] <= time_s <= self._rows[-1][0]:
            return None
        times, east, north = np.asarray(self._rows).T
        return float(np.interp(time_s, times, east)), float(np.interp(time_s, times, north))


class SimVehicle:
    """``run(duration_s)`` flies and streams until the duration ends or ``stop()`` (thread-safe).

    Frames go to ``frames_dir``, to ``stream`` (opened and closed by ``run``: the camera lives
    with the flight), or both.
    """

    def __init__(
        self,
        config: SimVehicleConfig,
        link: MavLink,
        frames_from: GeoRaster,
        camera: Camera,
        frames_dir: Path | None,
        out_dir: Path,
        stream: MjpegServer | None = None,
    ) -> None:
        if frames_dir is None and stream is None:
            raise OrthonavError("sim vehicle: give a frames folder, a camera stream, or both")
        for name, lat, lon in (
            ("start", config.start_lat, config.start_lon),
            ("target", config.target_lat, config.target_lon),
        ):
            if not frames_from.contains_latlon(lat, lon):
                raise OrthonavError(f"sim vehicle {name} {lat:.6f}, {lon:.6f} is outside {frames_from.path}")
        self.config, self.link, self.frames_from, self.camera = config, link, frames_from, camera
        self.frames_dir = Path(frames_dir) if frames_dir is not None else None
        self.out_dir, self.stream = Path(out_dir), stream
        self.rng = np.random.default_rng(config.seed)
        self.origin = LocalFrame(config.start_lat, config.start_lon)
        self.received: Counter[str] = Counter()  # by message type
        self.fix_types: Counter[int] = Counter()  # of GPS_INPUT
        self.frames_written = 0
        self.errors_m: dict[str, list[float]] = {t: [] for t in POSITION_TYPES}
        self._stop = threading.Event()
        self._boot_unix_s, self._mono0 = time.time(), time.monotonic()
        self._log: IO[str] | None = None
        self.begin(self._boot_unix_s)

    # --- clock ---------------------------------------------------------------------------
    def now(self) -> float:
        """UNIX seconds that never go backwards (monotonic from the run's start)."""
        return self._boot_unix_s + (time.monotonic() - self._mono0)

    def _boot_ms(self, now_s: float) -> int:
        return int((now_s - self._boot_unix_s) * 1000.0) & 0xFFFFFFFF

    # --- run -----------------------------------------------------------------------------
    def run(self, duration_s: float | None = None) -> dict:
        """Fly until ``duration_s`` (None: until ``stop()`` or Ctrl-C); returns the summary it wrote."""
        self.link.open()
        if self.frames_dir is not None:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        stream_url = self.stream.open().url if self.stream is not None else None
        write_json_atomic(
            self.out_dir / "config.json",
            {
                "vehicle": asdict(self.config),
                "url": self.link.url,
                "frames_dir": str(self.frames_dir) if self.frames_dir is not None else None,
                "stream": stream_url,
            },
        )
        self._boot_unix_s, self._mono0 = time.time(), time.monotonic()
        start = self.now()
        self.begin(start)
        slow = _Every(1.0, start)
        telemetry = _Every(self.config.telemetry_rate_hz, start)
        frames = _Every(self.config.frame_rate_hz, start)
        tick_s = 1.0 / self.config.physics_rate_hz
        try:
            with open_output(self.out_dir / "received.jsonl", "a") as self._log:
                while not self._stop.is_set() and (duration_s is None or self.now() - start < duration_s):
                    now = self.now()
                    self.advance(now)
                    self._receive(now)
                    if slow.due(now):
                        self._send_slow(now)
                    if telemetry.due(now):
                        self._send_telemetry(now)
                    if frames.due(now):
                        self._capture(now)
                    self._stop.wait(max(0.0, tick_s - (self.now() - now)))
        except KeyboardInterrupt:
            log.info("sim vehicle: interrupted, stopping")
        finally:
            self._log = None
            if self.stream is not None:
                self.stream.close()
            summary = self.summary(self.now() - start)
            write_json_atomic(self.out_dir / "summary.json", summary)
        return summary

    def stop(self) -> None:
        self._stop.set()

    # --- flight --------------------------------------------------------------------------
    def begin(self, start_s: float) -> None:
        """Put the vehicle at its start, heading for the target, at time ``start_s`` (``run`` does,
        with the wall clock)."""
        c = self.config
        heading = float(azimuth_deg(c.start_lat, c.start_lon, c.target_lat, c.target_lon))
        self.start_s = start_s
        self.kin = Kinematics(c.start_lat, c.start_lon, heading, c.speed_mps, start_s, c.max_turn_rate_dps)
        self.motion = Motion(0.0, 0.0, 0.0, *self.kin.velocity_en_mps)
        self.ins: InsSimulator | None = None
        self.nav = self._true_sample(start_s)
        self.truth = _Truth(self.origin, c.truth_history_s)
        self.truth.add(start_s, c.start_lat, c.start_lon)

    def advance(self, now: float) -> None:
        """Fly on to ``now``, steering on the autopilot's belief, then update that belief.

        ``run`` calls it every tick; tests may drive it on their own clock after :meth:`begin`.
        """
        dt = now - self.kin.time_s
        if dt <= 0:
            return
        c = self.config
        commanded = float(azimuth_deg(self.nav.lat, self.nav.lon, c.target_lat, c.target_lon))
        self.motion = self.kin.advance(dt, commanded)
        self.truth.add(now, self.kin.lat, self.kin.lon)
        if now - self.start_s < c.gnss_loss_s:
            self.nav = self._true_sample(now)
        elif self.ins is None:
            model = ImuErrorModel.preset(c.imu)
            truth = self._true_sample(now)
            self.ins = InsSimulator(
                model, self.rng, now, truth.lat, truth.lon, *self.kin.velocity_en_mps, self.kin.heading_deg
            )
            self.nav = self.ins.sample
            log.info("sim vehicle: GNSS lost at %.1f s, dead reckoning (%s IMU)", now - self.start_s, c.imu)
        else:
            m = self.motion
            self.nav = self.ins.step(now, m.accel_east_mps2, m.accel_north_mps2, m.yaw_rate_dps, c.alt_agl_m)

    def _true_sample(self, time_s: float) -> InsSample:
        east, north = self.kin.velocity_en_mps
        k = self.kin
        return InsSample(time_s, k.lat, k.lon, east, north, k.heading_deg, self.config.alt_agl_m)

    def _roll_deg(self) -> float:
        """Bank of a coordinated turn at the current yaw rate."""
        yaw_rate = math.radians(self.motion.yaw_rate_dps)
        return math.degrees(math.atan(self.config.speed_mps * yaw_rate / GRAVITY_MPS2))

    # --- streaming -----------------------------------------------------------------------
    def _send_slow(self, now: float) -> None:
        mavlink = dialect()
        self.link.heartbeat()
        self.link.send(mavlink.MAVLink_system_time_message(round(now * 1e6), self._boot_ms(now)))
        self.link.send(
            mavlink.MAVLink_gps_global_origin_message(
                round(self.config.start_lat * 1e7),
                round(self.config.start_lon * 1e7),
                round(self.config.ground_alt_msl_m * 1000),
                round(now * 1e6),
            )
        )

    def _send_telemetry(self, now: float) -> None:
        """What the autopilot believes: position/velocity/heading from ``self.nav``, true roll/pitch."""
        mavlink, nav, c = dialect(), self.nav, self.config
        boot_ms = self._boot_ms(now)
        alt_msl = c.ground_alt_msl_m + c.alt_agl_m
        east, north = self.origin.to_enu(nav.lat, nav.lon)
        yaw = math.radians((nav.heading_deg + 180.0) % 360.0 - 180.0)
        for msg in (
            mavlink.MAVLink_attitude_message(
                boot_ms,
                math.radians(self._roll_deg()),
                0.0,
                yaw,
                0.0,
                0.0,
                math.radians(self.motion.yaw_rate_dps),
            ),
            mavlink.MAVLink_global_position_int_message(
                boot_ms,
                round(nav.lat * 1e7),
                round(nav.lon * 1e7),
                round(alt_msl * 1000),
                round(c.alt_agl_m * 1000),
                round(nav.vel_north_mps * 100),
                round(nav.vel_east_mps * 100),
                0,
                round(nav.heading_deg * 100) % 36000,
            ),
            mavlink.MAVLink_local_position_ned_message(
                boot_ms, float(north), float(east), -c.alt_agl_m, nav.vel_north_mps, nav.vel_east_mps, 0.0
            ),
            mavlink.MAVLink_vfr_hud_message(
                c.speed_mps,
                math.hypot(nav.vel_east_mps, nav.vel_north_mps),
                round(nav.heading_deg) % 360,
                50,
                alt_msl,
                0.0,
            ),
        ):
            self.link.send(msg)

    def _capture(self, now: float) -> None:
        """Render the frame the camera sees at the TRUE pose and publish it under its capture time."""
        k = self.kin
        pose = TruePose(k.lat, k.lon, self.config.alt_agl_m, k.heading_deg, 0.0, self._roll_deg())
        photometric = Photometric.random(self.rng, self.config.photometric_strength)
        image = render_frame(self.frames_from, self.camera, pose, photometric, self.rng)
        if self.frames_dir is not None:
            with atomic_path(self.frames_dir / frame_filename(now)) as tmp:
                if not cv2.imwrite(str(tmp), image):
                    raise OrthonavError(f"{self.frames_dir}: cannot write frames there")
        if self.stream is not None:
            self.stream.publish(image, now)
        self.frames_written += 1

    # --- grading -------------------------------------------------------------------------
    def _receive(self, now: float) -> None:
        for msg in self.link.poll(100):
            kind = msg.get_type()
            self.received[kind] += 1
            if kind in POSITION_TYPES:
                self._record({"type": kind, "received_s": now, **self._grade(msg, now)})
            elif kind == "STATUSTEXT":
                self._record({"type": kind, "received_s": now, "severity": msg.severity, "text": msg.text})

    def _grade(self, msg: Any, now: float) -> dict:
        """Where the message puts the vehicle, when, and how far that is from the truth then."""
        position = self._position(msg)
        capture_s = self._capture_s(msg)
        record: dict[str, Any] = {"capture_s": capture_s, "age_s": now - capture_s, **position}
        if "lat" not in position:
            return record
        truth = self.truth.at(capture_s)
        if truth is None:
            return {**record, "problem": "capture time outside the kept true track"}
        east, north = self.origin.to_enu(position["lat"], position["lon"])
        true_lat, true_lon = self.origin.to_latlon(*truth)
        error = float(distance_m(position["lat"], position["lon"], float(true_lat), float(true_lon)))
        self.errors_m[msg.get_type()].append(error)
        return {
            **record,
            "true_lat": float(true_lat),
            "true_lon": float(true_lon),
            "error_m": error,
            "error_east_m": float(east) - truth[0],
            "error_north_m": float(north) - truth[1],
        }

    def _position(self, msg: Any) -> dict:
        """lat/lon (and accuracy) carried by a position message, or why it carries none."""
        if msg.get_type() == "GPS_INPUT":
            self.fix_types[msg.fix_type] += 1
            if msg.fix_type < 3:
                return {"fix_type": msg.fix_type}
            return {
                "lat": msg.lat * 1e-7,
                "lon": msg.lon * 1e-7,
                "fix_type": msg.fix_type,
                "horiz_accuracy_m": msg.horiz_accuracy,
            }
        if msg.get_type() == "GLOBAL_POSITION_SENSOR":
            return {"lat": msg.lat * 1e-7, "lon": msg.lon * 1e-7, "horiz_accuracy_m": msg.eph}
        if msg.get_type() == "ODOMETRY" and msg.frame_id not in LOCAL_FRAMES:
            return {"problem": f"ODOMETRY frame_id {msg.frame_id} is not a local NED/FRD frame"}
        lat, lon = self.origin.to_latlon(msg.y, msg.x)
        return {"lat": float(lat), "lon": float(lon), "sigma_north_m": _sigma(msg)}

    def _capture_s(self, msg: Any) -> float:
        """When the message's position was true: GLOBAL_POSITION_SENSOR stamps its sending and
        says how long before that its position was measured."""
        if msg.get_type() == "GLOBAL_POSITION_SENSOR":
            return self._unix_s(msg.time_usec - msg.processing_time)
        return self._unix_s(msg.time_usec if hasattr(msg, "time_usec") else msg.usec)

    def _unix_s(self, usec: int) -> float:
        """A MAVLink timestamp as UNIX seconds: large ones are UNIX, small ones since our boot."""
        return usec * 1e-6 if usec >= UNIX_USEC_MIN else self._boot_unix_s + usec * 1e-6

    def _record(self, data: dict) -> None:
        if self._log is not None:
            self._log.write(json.dumps(data) + "\n")
            self._log.flush()

    # --- summary -------------------------------------------------------------------------
    def summary(self, duration_s: float) -> dict:
        c, k = self.config, self.kin
        return {
            "duration_s": round(duration_s, 3),
            "received": dict(self.received),
            "errors": {t: _error_stats(e) for t, e in self.errors_m.items() if e},
            "gps_input_fix_types": {str(fix): n for fix, n in sorted(self.fix_types.items())},
            "positions_with_3d_fix": sum(n for fix, n in self.fix_types.items() if fix >= 3),
            "frames": self.frames_written,
            "true_distance_to_target_m": round(
                float(distance_m(k.lat, k.lon, c.target_lat, c.target_lon)), 1
            ),
            "ins_error_m": round(float(distance_m(k.lat, k.lon, self.nav.lat, self.nav.lon)), 2),
            "link": self.link.stats.to_dict(),
            **({"stream": self.stream.stats.to_dict()} if self.stream is not None else {}),
        }


def _sigma(msg: Any) -> float | None:
    """1-sigma north (m) of a pose covariance in MAVLink's layout, None when unknown."""
    cov = msg.covariance if hasattr(msg, "covariance") else msg.pose_covariance
    return math.sqrt(cov[0]) if math.isfinite(cov[0]) and cov[0] >= 0 else None


def _error_stats(errors_m: list[float]) -> dict:
    err = np.asarray(errors_m, float)
    return {
        "count": len(err),
        "median_m": round(float(np.median(err)), 2),
        "p95_m": round(float(np.percentile(err, 95)), 2),
        "max_m": round(float(err.max()), 2),
    }
