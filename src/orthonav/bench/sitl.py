"""``orthonav bench sitl``: orthonav in the loop with ArduPilot's real firmware (SITL).

ArduPilot's SITL binary (its flight code and EKF3 against a physics model) flies an AUTO
mission. This module is the rest of the world: a ground station on the autopilot's second serial
port (parameters, the mission, arming, the jamming) and the camera: frames rendered from an
orthophoto at the vehicle's true pose (SIMSTATE), written into a folder that the real
``orthonav fly`` process watches. ``fly`` talks to the autopilot's first serial port as a companion
computer would. GPS 1 is SITL's simulated receiver, GPS 2 is orthonav (GPS_INPUT); once the
vehicle is at cruise altitude GPS 1 is switched off (``SIM_GPS_DISABLE``), and the autopilot
must finish its mission on orthonav; or GPS 1 is moved hundreds of metres (``SIM_GPS_GLITCH``,
a spoofer), and the question is whom the autopilot follows. Every figure is measured against SITL's truth: the
autopilot's own position (GLOBAL_POSITION_INT) against SIMSTATE, the landing point against the
planned one, orthonav's positions against the true track at their time. The same mission without
orthonav is the twin.

The map is another year of the same area than the frames (cross-date); the cruise altitude is
one where a frame covers enough of the map to match (300 m: 70 pixels of a 5 m/px map).
Everything runs in real time (SITL ``--speedup 1``): the companion keeps wall-clock time, as on
a vehicle.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import queue
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from orthonav.atomic import atomic_path, write_json_atomic
from orthonav.bench.faults import child_process, free_udp_port
from orthonav.bench.machine import LoadWatch, machine_line
from orthonav.bench.scoring import quantiles
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames import frame_filename
from orthonav.frames.render import TruePose, render_frame, sees_only_ground
from orthonav.geo import GeoRaster, LocalFrame, destination, distance_m
from orthonav.mavlink.link import dialect

CLI = [sys.executable, "-m", "orthonav.cli.main"]
GCS_SYSTEM, GCS_COMPONENT = 255, 190
STOP_GRACE_S = 20.0  # fly writes its summary and SITL closes its logs on SIGTERM
AUTO_MODE = {"copter": 3, "plane": 10}  # each vehicle's HEARTBEAT custom_mode of AUTO
PLANE_TAKEOFF_PITCH_DEG = 15.0  # NAV_TAKEOFF's minimum pitch for a plane
PLANE_RTL = 11
ARMING_CHECKS = (1 << 21) - 2  # ARMING_CHECK bits 1..20, each check named
ARMING_GPS_LOCK, ARMING_VISUAL_ODOMETRY = 1 << 3, 1 << 18
COPTER_LAND = 9
WRONG_SIGMAS = 3.0
WRONG_M = 50.0
# The autopilot's words for trouble with its estimate or a failsafe it took; ArduCopter's "Dead
# Reckoning started / stopped / timeout" bracket the spans EKF3 navigated on its drag model alone.
TROUBLE = re.compile(
    r"failsafe|variance|glitch|dead reckoning"
    r"|EKF.*(?:stopped|lane|switch|reset|fail)|GPS.*(?:lost|unhealthy)",
    re.I,
)
EKF_FAILSAFE = re.compile(r"EKF.*failsafe|failsafe.*EKF|EKF variance", re.I)
# fly's events (orthonav.mavlink.companion) when it answers a spoofing warning, and when the
# autopilot accepts the answer (a source set is acknowledged; a parameter is not awaited).
SPOOFING_ANSWER = {
    "answer_sent_after_s": re.compile(r"made primary|source set \d+ \(ExternalNav, orthonav\) requested"),
    "answer_accepted_after_s": re.compile(r"source set \d+ \(ExternalNav, orthonav\) selected"),
}


@dataclass(frozen=True)
class SitlScenario:
    """One flight: the vehicle, whether orthonav feeds it, and what happens to GPS 1."""

    name: str
    vehicle: str
    orthonav: bool
    gnss: str  # "off": SIM_GPS_DISABLE takes SITL's GPS 1 away; "spoofed": SIM_GPS_GLITCH moves it
    description: str
    gimbal: bool = True  # a nadir-stabilised camera (fly --nadir-gimbal); False: fixed to the body
    # gps_input: orthonav is GPS 2. vision, odometry: VISION_POSITION_ESTIMATE or ODOMETRY into
    # EKF3's ExternalNav, its second source set, which the ground station selects when GNSS goes
    # (a spoofer it does not see: there only fly --on-spoofing switch-source selects it).
    output: str = "gps_input"
    # A downward optical-flow sensor and lidar: EKF3's velocity below the lidar's range (FLOW_PARAMS).
    flow: bool = False
    on_spoofing: str = "warn"  # fly --on-spoofing
    frame_velocity: bool = False  # fly --frame-velocity
    independent_attitude: bool = False  # fly --independent-attitude: a body camera's fixes fused without GNSS


SCENARIOS = {
    s.name: s
    for s in (
        SitlScenario(
            "copter-gnss-off",
            "copter",
            True,
            "off",
            "GPS 1 off at cruise altitude; orthonav is GPS 2, its positions alone (fly --no-frame-velocity)",
        ),
        SitlScenario("copter-gnss-off-alone", "copter", False, "off", "the same mission without orthonav"),
        SitlScenario(
            "copter-gnss-off-velocity",
            "copter",
            True,
            "off",
            "as copter-gnss-off, fly --frame-velocity: orthonav's GPS 2 velocity measured between its "
            "frames, at the accuracy its filter gives it",
            frame_velocity=True,
        ),
        SitlScenario(
            "copter-gnss-off-body-camera",
            "copter",
            True,
            "off",
            "as copter-gnss-off, the camera fixed to the body (it tilts 20-30 deg while accelerating)",
            gimbal=False,
        ),
        SitlScenario(
            "copter-gnss-off-extnav",
            "copter",
            True,
            "off",
            "as copter-gnss-off, orthonav as EKF3's ExternalNav (VISION_POSITION_ESTIMATE), the source "
            "set switched to it when GPS 1 goes",
            output="vision",
        ),
        SitlScenario(
            "copter-gnss-off-odometry",
            "copter",
            True,
            "off",
            "as copter-gnss-off-extnav, the positions sent as ODOMETRY",
            output="odometry",
        ),
        SitlScenario(
            "copter-gnss-off-flow",
            "copter",
            True,
            "off",
            "as copter-gnss-off, with a downward optical-flow sensor and lidar: EKF3's horizontal "
            "velocity from the flow below FLOW_SWITCH_M, where orthonav's fixes stop short of the ground",
            flow=True,
        ),
        SitlScenario(
            "copter-gnss-off-flow-velocity",
            "copter",
            True,
            "off",
            "as copter-gnss-off-flow, fly --frame-velocity: orthonav's GPS 2 velocity measured between "
            "its frames, at the accuracy its filter gives it",
            flow=True,
            frame_velocity=True,
        ),
        SitlScenario(
            "copter-gnss-off-flow-alone",
            "copter",
            False,
            "off",
            "as copter-gnss-off-flow, without orthonav: the flow sensor and lidar alone",
            flow=True,
        ),
        SitlScenario(
            "plane-gnss-off",
            "plane",
            True,
            "off",
            "ArduPlane: the route, loiter turns at its end and return to loiter over home; GPS 1 off at "
            "cruise altitude, orthonav is GPS 2",
        ),
        SitlScenario(
            "plane-gnss-off-body-camera",
            "plane",
            True,
            "off",
            "as plane-gnss-off, the camera fixed to the body (it banks with the plane)",
            gimbal=False,
        ),
        SitlScenario(
            "plane-gnss-off-body-camera-fused",
            "plane",
            True,
            "off",
            "as plane-gnss-off-body-camera, fly --independent-attitude: its correlation fixes fused "
            "without GNSS, as before that rule (does the plane's tilt follow them?)",
            gimbal=False,
            independent_attitude=True,
        ),
        SitlScenario(
            "plane-gnss-off-velocity",
            "plane",
            True,
            "off",
            "as plane-gnss-off, fly --frame-velocity: orthonav's GPS 2 velocity measured between its "
            "frames, at the accuracy its filter gives it",
            frame_velocity=True,
        ),
        SitlScenario(
            "copter-gnss-spoofed",
            "copter",
            True,
            "spoofed",
            "GPS 1 moved by SitlConfig.spoof_m at cruise altitude (SIM_GPS_GLITCH); orthonav is GPS 2",
        ),
        SitlScenario(
            "copter-gnss-spoofed-switch",
            "copter",
            True,
            "spoofed",
            "as copter-gnss-spoofed, fly --on-spoofing switch-gps: orthonav makes its GPS 2 the primary "
            "once the autopilot stays far from its fixes",
            on_spoofing="switch-gps",
        ),
        SitlScenario(
            "copter-gnss-spoofed-extnav-switch",
            "copter",
            True,
            "spoofed",
            "as copter-gnss-off-extnav (orthonav EKF3's ExternalNav in source set 2), GPS 1 spoofed as in "
            "copter-gnss-spoofed; fly --on-spoofing switch-source selects set 2 once the autopilot stays far "
            "from its fixes",
            output="vision",
            on_spoofing="switch-source",
        ),
    )
}
DEFAULT_SCENARIOS = ("copter-gnss-off-velocity", "copter-gnss-off-alone")
EXTNAV_OUTPUTS = ("vision", "odometry")
# EKF3 weighs an ExternalNav position by the last accuracy GPS 1 reported (stale once GPS 1 is
# gone), floored at EK3_POSNE_M_NSE, ahead of the message's own. At a receiver's half metre its
# gate turns orthonav's fixes away for their ordinary scatter: every core dead-reckons without a
# velocity until it resets onto them, and their error scores hand the primary back and forth.
# The floor is set to the order of the sigma orthonav claims at cruise height.
EXTNAV_POS_NOISE_M = 5.0
# The landing aid: SITL's optical-flow sensor and a lidar of FLOW_LIDAR_RANGE_M (a long-range one).
# EKF3 counts flow as a position (relative) only while the lidar pins its height above the ground,
# and a flow sensor resolves the ground's motion only that low: source set 2 (position still from
# GPS, that is orthonav's GPS 2 while its fixes last, velocity from the flow, height from the
# barometer) is selected by the ground station below FLOW_SWITCH_M, inside the lidar's range with
# room for tilt. On a vehicle an RC switch or a script selects it the same way.
FLOW_LIDAR_RANGE_M = 100.0
FLOW_SWITCH_M = 90.0
FLOW_PARAMS: dict[str, float] = {
    "SIM_FLOW_ENABLE": 1,
    "FLOW_TYPE": 10,  # SITL's flow sensor
    "RNGFND1_TYPE": 100,  # SITL's rangefinder
    "RNGFND1_ORIENT": 25,  # facing down
    "RNGFND1_MAX_CM": FLOW_LIDAR_RANGE_M * 100,
    "EK3_FLOW_USE": 1,  # flow for navigation
    "EK3_SRC2_POSXY": 3,
    "EK3_SRC2_VELXY": 5,
    "EK3_SRC2_POSZ": 1,
    "EK3_SRC2_VELZ": 0,
    "EK3_SRC2_YAW": 1,
    # ArduPilot's default fuses every set's velocity source at once: the flow's at cruise height too.
    "EK3_SRC_OPTIONS": 0,
}


@dataclass(frozen=True)
class SitlConfig:
    """The mission, the camera and the timing; written beside the numbers."""

    scenarios: tuple[str, ...] = DEFAULT_SCENARIOS
    alt_m: float = 300.0
    # Legs from home as (east, north) metres: a 2 km route, then RTL home and land.
    route_m: tuple[tuple[float, float], ...] = ((800.0, 0.0), (800.0, 400.0), (0.0, 400.0))
    hold_s: float = 0.0  # at the route's last waypoint
    speed_mps: float = 10.0
    climb_mps: float = 5.0
    descent_mps: float = 3.0
    frame_rate_hz: float = 2.0
    min_frame_alt_m: float = 40.0  # below this the frames see less ground than a map tile
    hfov_deg: float = 60.0
    home_alt_msl_m: float = 560.0
    timeout_s: float = 1200.0
    ekf_ready_timeout_s: float = 120.0
    spoof_m: tuple[float, float] = (300.0, 300.0)  # where a spoofer moves GPS 1: (east, north) metres
    # The plane loiters this many turns at the route's end, then returns (RTL) and loiters over
    # home for plane_home_s before the flight ends: ArduPlane does not land by itself.
    loiter_turns: float = 3.0
    loiter_radius_m: float = 150.0
    plane_home_s: float = 60.0
    # The age of the state orthonav sends (the filter's, dead-reckoned to the newest telemetry):
    # without it ArduPilot assumes its default lag for a MAVLink GPS.
    gps_input_delay_ms: int = 50
    # Parameters a flight sets over the scenario's (a fault flight's tighter loiter, say).
    extra_params: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        unknown = sorted(set(self.scenarios) - set(SCENARIOS))
        if unknown:
            raise OrthonavError(
                f"SITL scenarios {', '.join(unknown)}: expected some of {', '.join(SCENARIOS)}"
            )
        if not self.scenarios:
            raise OrthonavError("SITL bench: no scenario")
        if self.alt_m < 2 * self.min_frame_alt_m or not self.route_m:
            raise OrthonavError(
                f"SITL bench: altitude {self.alt_m:g} m and a route of at least one leg expected"
            )

    @property
    def camera(self) -> Camera:
        return Camera.from_hfov(640, 480, self.hfov_deg)


def binary(sitl_dir: Path, vehicle: str) -> Path:
    """The SITL binary of ``vehicle`` in ``sitl_dir``, or a clear error where it is absent."""
    path = sitl_dir / f"ardu{vehicle}"
    if not (path.is_file() and os.access(path, os.X_OK)):
        raise OrthonavError(
            f"{path}: no ArduPilot SITL binary for the {vehicle} (pass --sitl-dir, the folder with "
            f"arducopter/arduplane and their .parm files)"
        )
    return path


def vehicle_params(config: SitlConfig, scenario: SitlScenario) -> dict[str, float]:
    """What a user sets (documented on the SITL page), plus the ground station's streams on
    SERIAL1. GPS 2 is orthonav only where it flies: the twin is the autopilot alone."""
    params = {
        "GPS1_TYPE": 1,
        "GPS2_TYPE": 14 if scenario.orthonav else 0,
        "GPS_AUTO_SWITCH": 1,
        "GPS_PRIMARY": 0,
        "GPS2_DELAY_MS": config.gps_input_delay_ms if scenario.orthonav else 0,
        # ArduPilot's GPS-lock pre-arm check asks every GPS for a 3-D fix, and orthonav has none
        # on the ground (no map-scale view): every other check stays, the EKF's position included.
        "ARMING_CHECK": ARMING_CHECKS - ARMING_GPS_LOCK if scenario.orthonav else 1,
        "AUTO_OPTIONS": 3,  # arm in AUTO and take off without raising the throttle (no RC here)
        "WPNAV_SPEED": config.speed_mps * 100,
        "WPNAV_SPEED_UP": config.climb_mps * 100,
        "WPNAV_SPEED_DN": config.descent_mps * 100,
        "RTL_ALT": config.alt_m * 100,
        "TERRAIN_ENABLE": 0,
        "SR0_EXTRA1": 25,  # ATTITUDE for the companion: a copter's tilt changes fast
        "SR0_POSITION": 10,
        # GPS_RAW_INT and GPS2_RAW: the search held on the GNSS until the first visual fix, and
        # which receiver is orthonav's when it must be made the primary (fly --on-spoofing)
        "SR0_EXT_STAT": 2,
        "SR0_EXTRA3": 5,
        "SR1_EXTRA1": 50,  # SIMSTATE (truth) and ATTITUDE: the camera's pose
        "SR1_POSITION": 10,
        "SR1_EXT_STAT": 2,
        "SR1_EXTRA3": 2,
    }
    if scenario.vehicle == "plane":
        params = {k: v for k, v in params.items() if not k.startswith(("WPNAV_", "AUTO_OPTIONS", "RTL_ALT"))}
        params |= {
            "RTL_ALTITUDE": config.alt_m,  # metres: return at cruise height, where frames match
            "RTL_AUTOLAND": 0,
            "WP_LOITER_RAD": config.loiter_radius_m,
        }
    if scenario.output in EXTNAV_OUTPUTS:
        params |= {
            "GPS2_TYPE": 0,
            "GPS2_DELAY_MS": 0,
            # As the GPS lock for GPS 2: no map-scale view on the ground, so no ExternalNav yet.
            "ARMING_CHECK": ARMING_CHECKS - ARMING_VISUAL_ODOMETRY,
            "VISO_TYPE": 1,  # MAVLink
            "EK3_POSNE_M_NSE": EXTNAV_POS_NOISE_M,
            # Source set 2: position from ExternalNav, height from the barometer, yaw from the
            # compass, no velocity: VISION_POSITION_ESTIMATE has none, and ODOMETRY's is the
            # autopilot's own fed back (fused, it would close a loop); GPS velocity not mixed in.
            "EK3_SRC2_POSXY": 6,
            "EK3_SRC2_VELXY": 0,
            "EK3_SRC2_POSZ": 1,
            "EK3_SRC2_YAW": 1,
            "EK3_SRC_OPTIONS": 0,
        }
    if scenario.flow:
        params |= FLOW_PARAMS

    return params | dict(config.extra_params)


def extra_param(text: str) -> tuple[str, float]:
    """``NAME=VALUE`` as an ArduPilot parameter set over a scenario's (``SitlConfig.extra_params``):
    an experiment's, so a typo must not fly as a parameter ArduPilot silently ignores."""
    name, sep, value = text.partition("=")
    name = name.strip()
    if not sep or not re.fullmatch(r"[A-Z][A-Z0-9_]{0,15}", name):
        raise OrthonavError(
            f"SITL parameter {text!r}: expected NAME=VALUE, NAME an ArduPilot parameter (capitals, "
            f"digits, underscores, at most 16 characters)"
        )
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not math.isfinite(number):
        raise OrthonavError(f"SITL parameter {name}: expected a finite number, got {value.strip()!r}")
    return name, number


def parm_text(params: dict[str, float]) -> str:
    """A .parm file: every value exactly (a bitmask such as ARMING_CHECK loses its low bits in
    six significant digits)."""
    return "".join(f"{name} {value:.15g}\n" for name, value in params.items())


# --- the autopilot's ground-station side -----------------------------------------------------


@dataclass
class Track:
    """What the ground station heard, stamped with wall-clock arrival time."""

    truth: list[tuple[float, float, float]] = field(default_factory=list)  # (t, lat, lon)
    estimate: list[tuple[float, float, float, float]] = field(
        default_factory=list
    )  # (t, lat, lon, truth error)
    # (t, roll, pitch, yaw) in degrees: SIMSTATE's true attitude and the autopilot's estimate
    # (ATTITUDE), what a body-fixed camera's fixes are made with
    true_attitude: list[tuple[float, float, float, float]] = field(default_factory=list)
    attitude: list[tuple[float, float, float, float]] = field(default_factory=list)
    texts: list[tuple[float, str]] = field(default_factory=list)
    modes: list[tuple[float, int]] = field(default_factory=list)
    armed_at: float | None = None
    disarmed_at: float | None = None
    reached: list[tuple[float, int]] = field(default_factory=list)

    def truth_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        times, lats, lons = np.asarray(self.truth, float).T
        return np.interp(t, times, lats), np.interp(t, times, lons)


def _degrees(msg: Any) -> tuple[float, float, float]:
    """A SIMSTATE's or ATTITUDE's roll, pitch and yaw in degrees."""
    return math.degrees(msg.roll), math.degrees(msg.pitch), math.degrees(msg.yaw)


class GroundStation:
    """A pymavlink connection on SITL's SERIAL1: reads everything in a thread into a
    :class:`Track`, keeps the newest truth for the camera, and queues replies for commands."""

    def __init__(self, port: int) -> None:
        from pymavlink import mavutil

        os.environ.setdefault("MAVLINK20", "1")
        self.conn = mavutil.mavlink_connection(
            f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM, source_component=GCS_COMPONENT, dialect="all"
        )
        self.track = Track()
        self.replies: queue.Queue = queue.Queue()
        self.latest: dict[str, Any] = {}
        self.arrived: dict[str, float] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True, name="sitl-gcs")

    def __enter__(self) -> GroundStation:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.conn.close()

    def _read(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is None or msg.get_srcComponent() != 1:
                continue
            self._note(msg, time.time())

    def _note(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        self.latest[kind], self.arrived[kind] = msg, now
        track = self.track
        if kind == "SIMSTATE":
            track.truth.append((now, msg.lat * 1e-7, msg.lng * 1e-7))
            track.true_attitude.append((now, *_degrees(msg)))
        elif kind == "ATTITUDE":
            track.attitude.append((now, *_degrees(msg)))
        elif kind == "GLOBAL_POSITION_INT" and track.truth and track.armed_at is not None:
            # From arming: before its origin is set an autopilot reports positions about 0, 0
            # (ArduPlane does, thousands of kilometres from the truth), and none arms without one.
            _, lat, lon = track.truth[-1]
            est = (msg.lat * 1e-7, msg.lon * 1e-7)
            track.estimate.append((now, *est, float(distance_m(lat, lon, *est))))
        elif kind == "STATUSTEXT":
            track.texts.append((now, msg.text))
        elif kind == "HEARTBEAT":
            self._heartbeat(msg, now)
        elif kind == "MISSION_ITEM_REACHED":
            track.reached.append((now, msg.seq))
        elif kind in ("COMMAND_ACK", "MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK", "PARAM_VALUE"):
            self.replies.put(msg)

    def _heartbeat(self, msg: Any, now: float) -> None:
        track = self.track
        armed = bool(msg.base_mode & dialect().MAV_MODE_FLAG_SAFETY_ARMED)
        if not track.modes or track.modes[-1][1] != msg.custom_mode:
            track.modes.append((now, msg.custom_mode))
        if armed and track.armed_at is None:
            track.armed_at = now
        if not armed and track.armed_at is not None and track.disarmed_at is None:
            track.disarmed_at = now

    # --- commands ---------------------------------------------------------------------------

    def wait_for(self, what: str, predicate: Any, timeout_s: float, sitl: subprocess.Popen) -> None:
        deadline = time.monotonic() + timeout_s
        while not predicate():
            if sitl.poll() is not None:
                raise OrthonavError(f"SITL exited with code {sitl.returncode} while waiting for {what}")
            if time.monotonic() > deadline:
                raise OrthonavError(f"SITL: no {what} within {timeout_s:.0f} s")
            time.sleep(0.1)

    def _reply(self, kinds: tuple[str, ...], timeout_s: float = 5.0, match: Any = None) -> Any:
        """The next queued reply of one of ``kinds`` (and ``match``); others are dropped."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                msg = self.replies.get(timeout=max(0.01, deadline - time.monotonic()))
            except queue.Empty:
                break
            if msg.get_type() in kinds and (match is None or match(msg)):
                return msg
        raise OrthonavError(f"SITL: no {' or '.join(kinds)} within {timeout_s:.0f} s")

    def set_param(self, name: str, value: float) -> None:
        """PARAM_SET until the autopilot echoes the value (it also volunteers other PARAM_VALUEs)."""
        mav = dialect()
        for _ in range(3):
            self.conn.mav.param_set_send(1, 1, name.encode(), float(value), mav.MAV_PARAM_TYPE_REAL32)
            try:
                self._reply(
                    ("PARAM_VALUE",),
                    2.0,
                    lambda m: m.param_id == name and math.isclose(m.param_value, value, abs_tol=1e-6),
                )
                return
            except OrthonavError:
                continue
        raise OrthonavError(f"SITL: parameter {name} not set to {value:g}")

    def command(self, command: int, *params: float) -> None:
        padded = [*params, *[0.0] * (7 - len(params))]
        self.conn.mav.command_long_send(1, 1, command, 0, *padded)
        ack = self._reply(("COMMAND_ACK",))
        if ack.result != dialect().MAV_RESULT_ACCEPTED:
            raise OrthonavError(f"SITL refused command {command} (result {ack.result})")

    def upload_mission(self, items: list[Any]) -> None:
        """The MAVLink mission protocol: count, then each item the autopilot asks for."""
        mav = dialect()
        self.conn.mav.mission_count_send(1, 1, len(items), mav.MAV_MISSION_TYPE_MISSION)
        while True:
            msg = self._reply(("MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"))
            if msg.get_type() == "MISSION_ACK":
                if msg.type != mav.MAV_MISSION_ACCEPTED:
                    raise OrthonavError(f"SITL refused the mission (MISSION_ACK type {msg.type})")
                return
            self.conn.mav.send(items[msg.seq])

    def set_mode(self, custom_mode: int) -> None:
        mav = dialect()
        self.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode)

    def arm(self) -> None:
        self.command(dialect().MAV_CMD_COMPONENT_ARM_DISARM, 1)


def mission_items(config: SitlConfig, home: tuple[float, float], vehicle: str = "copter") -> list[Any]:
    """Home, take off to the cruise altitude, the route's legs, return to launch (a copter lands;
    a plane loiters ``loiter_turns`` at the route's end first, and over home after)."""
    mav = dialect()
    frame = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT

    def item(seq: int, command: int, lat: float, lon: float, alt: float, param1: float = 0.0) -> Any:
        return mav.MAVLink_mission_item_int_message(
            1, 1, seq, frame, command, 0, 1, param1, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), alt, 0
        )

    plane = vehicle == "plane"
    items = [
        item(0, mav.MAV_CMD_NAV_WAYPOINT, *home, 0.0),
        item(1, mav.MAV_CMD_NAV_TAKEOFF, *home, config.alt_m, PLANE_TAKEOFF_PITCH_DEG if plane else 0.0),
    ]
    for leg, (east, north) in enumerate(config.route_m, start=1):
        last = leg == len(config.route_m)
        lat, lon = _offset(home, east, north)
        # param1: a plane's turns around its loiter (radius WP_LOITER_RAD), a copter's hold in seconds
        command, param1 = mav.MAV_CMD_NAV_WAYPOINT, (config.hold_s if last else 0.0)
        if plane and last:
            command, param1 = mav.MAV_CMD_NAV_LOITER_TURNS, config.loiter_turns
        items.append(item(len(items), command, lat, lon, config.alt_m, param1))
    items.append(item(len(items), mav.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0, 0.0, 0.0))
    return items


def _offset(home: tuple[float, float], east_m: float, north_m: float) -> tuple[float, float]:
    lat, lon = destination(*home, 90.0, east_m) if east_m else home
    return destination(lat, lon, 0.0, north_m) if north_m else (lat, lon)


# --- the camera ------------------------------------------------------------------------------


class CameraRig(threading.Thread):
    """Renders what the nadir-looking camera (on a gimbal, or fixed to the body) sees at the
    vehicle's true pose, at
    ``rate_hz`` while it is high enough, into ``folder`` named by capture time (atomically)."""

    def __init__(
        self, gcs: GroundStation, raster: GeoRaster, config: SitlConfig, folder: Path, gimbal: bool
    ) -> None:
        super().__init__(daemon=True, name="sitl-camera")
        self.gcs, self.raster, self.config, self.folder, self.gimbal = gcs, raster, config, folder, gimbal
        self.frames = 0
        self._halt = threading.Event()

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=10)

    def run(self) -> None:
        period = 1.0 / self.config.frame_rate_hz
        next_s = time.monotonic()
        while not self._halt.wait(max(0.0, next_s - time.monotonic())):
            next_s += period
            captured = self.gcs.arrived.get("SIMSTATE", 0.0)  # the time the pose was true
            pose = self._pose()
            if pose is None:
                continue
            if not sees_only_ground(self.config.camera, pose):
                continue
            image = render_frame(self.raster, self.config.camera, pose)
            with atomic_path(self.folder / frame_filename(captured)) as tmp:
                cv2.imwrite(str(tmp), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
            self.frames += 1

    def _pose(self) -> TruePose | None:
        state, position = self.gcs.latest.get("SIMSTATE"), self.gcs.latest.get("GLOBAL_POSITION_INT")
        if state is None or position is None or position.relative_alt / 1000.0 < self.config.min_frame_alt_m:
            return None
        return TruePose(
            lat=state.lat * 1e-7,
            lon=state.lng * 1e-7,
            alt_agl_m=position.relative_alt / 1000.0,  # the barometer's: SIMSTATE has no height
            yaw_deg=math.degrees(state.yaw) % 360.0,
            pitch_deg=0.0 if self.gimbal else math.degrees(state.pitch),
            roll_deg=0.0 if self.gimbal else math.degrees(state.roll),
        )


# --- one flight ------------------------------------------------------------------------------


def free_instance(tries: int = 20) -> int:
    """A SITL instance number whose TCP ports (5760 + 10 x instance and the nine above: its
    other serial ports) are free, so two flights on one machine do not collide."""
    for instance in range(tries):
        base = 5760 + 10 * instance
        if all(_tcp_free(port) for port in range(base, base + 10)):
            return instance
    raise OrthonavError(
        f"SITL: no free instance among the first {tries} (TCP ports 5760-{5760 + 10 * tries})"
    )


def _tcp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def sitl_command(
    sitl_dir: Path, vehicle: str, parm: Path, home: tuple[float, float, float], ports: tuple[int, int]
) -> list[str]:
    defaults = ",".join(str(p) for p in (sitl_dir / f"{vehicle}.parm", parm))
    model = "+" if vehicle == "copter" else "plane"
    return [
        str(binary(sitl_dir, vehicle)),
        "-S",
        "-w",
        "--model",
        model,
        "--speedup",
        "1",
        "--defaults",
        defaults,
        f"-I{free_instance()}",
        "--home",
        f"{home[0]:.7f},{home[1]:.7f},{home[2]:.1f},0",
        "--serial0",
        f"udpclient:127.0.0.1:{ports[0]}",
        "--serial1",
        f"udpclient:127.0.0.1:{ports[1]}",
    ]


def fly_command(package: Path, frames: Path, port: int, log_dir: Path, scenario: SitlScenario) -> list[str]:
    return [
        *CLI,
        "fly",
        "--map",
        str(package),
        "--frames",
        str(frames),
        "--connect",
        f"udpin:127.0.0.1:{port}",
        "--output",
        scenario.output,
        "--log-dir",
        str(log_dir),
        *(["--nadir-gimbal"] if scenario.gimbal else []),
        *(["--independent-attitude"] if scenario.independent_attitude else []),
        "--frame-velocity" if scenario.frame_velocity else "--no-frame-velocity",
        "--on-spoofing",
        scenario.on_spoofing,
    ]


class FlightFault:
    """What a fault flight (``orthonav.bench.sitl_faults``) does to the flight of
    :func:`run_scenario`; this one does nothing."""

    def links(self, stack: ExitStack, companion_port: int, camera: Path) -> tuple[int, Path]:
        """The UDP port SITL's SERIAL0 sends to and the folder the camera writes: the companion's
        own, or a relay's in front of them (entered on ``stack``)."""
        return companion_port, camera

    def on_ground(self, gcs: GroundStation, sitl: subprocess.Popen, flight: dict) -> None:
        """Once the EKF is ready, before the mission is uploaded."""

    def in_flight(self, gcs: GroundStation, flight: dict) -> None:
        """Twice a second from GNSS loss until the flight ends."""

    def grade(self, row: dict, root: Path, flight: dict) -> dict:
        """The graded row with what the fault adds."""
        return row


def run_scenario(
    scenario: SitlScenario,
    config: SitlConfig,
    sitl_dir: Path,
    package: Path,
    frames_from: Path,
    root: Path,
    fault: FlightFault | None = None,
) -> dict:
    """Fly ``scenario`` once (with ``fault`` where given); the graded row (see :func:`grade`)."""
    fault = fault or FlightFault()
    if root.exists():
        shutil.rmtree(root)
    (root / "sitl").mkdir(parents=True)
    (root / "camera").mkdir()
    parm = root / "scenario.parm"
    parm.write_text(parm_text(vehicle_params(config, scenario)))
    ports = (free_udp_port(), free_udp_port())
    flight: dict[str, Any] = {"gnss_off_at": None}
    with ExitStack() as stack:
        raster = stack.enter_context(GeoRaster(frames_from))
        home = raster.center_latlon
        gcs = stack.enter_context(GroundStation(ports[1]))
        serial0, camera_folder = fault.links(stack, ports[0], root / "camera")
        if scenario.orthonav:
            stack.enter_context(
                child_process(
                    fly_command(package, root / "camera", ports[0], root / "fly", scenario),
                    root / "fly.out",
                    cwd=root,
                    grace_s=STOP_GRACE_S,
                )
            )
        sitl = stack.enter_context(
            child_process(
                sitl_command(
                    sitl_dir, scenario.vehicle, parm, (*home, config.home_alt_msl_m), (serial0, ports[1])
                ),
                root / "sitl.out",
                cwd=root / "sitl",
                grace_s=STOP_GRACE_S,
            )
        )
        camera = CameraRig(gcs, raster, config, camera_folder, scenario.gimbal)
        camera.start()
        stack.callback(camera.stop)
        try:
            _fly_mission(gcs, sitl, scenario, config, home, flight, fault)
        finally:
            write_json_atomic(root / "track.json", {"home": home, **flight, **asdict(gcs.track)})
    return fault.grade(grade(scenario, config, gcs.track, flight, home, root, camera.frames), root, flight)


def _fly_mission(
    gcs: GroundStation,
    sitl: subprocess.Popen,
    scenario: SitlScenario,
    config: SitlConfig,
    home: tuple[float, float],
    flight: dict,
    fault: FlightFault,
) -> None:
    """Wait for the EKF, upload, arm in AUTO, jam GPS 1 at cruise altitude, wait for the landing."""
    track = gcs.track
    gcs.wait_for(
        "EKF using GPS",
        lambda: any("is using GPS" in text for _, text in track.texts),
        config.ekf_ready_timeout_s,
        sitl,
    )
    fault.on_ground(gcs, sitl, flight)
    gcs.upload_mission(mission_items(config, home, scenario.vehicle))
    gcs.set_mode(AUTO_MODE[scenario.vehicle])
    _arm_when_ready(gcs, sitl)
    at_cruise = lambda: _rel_alt(gcs) >= config.alt_m - 5.0  # noqa: E731
    gcs.wait_for("cruise altitude", at_cruise, config.alt_m / config.climb_mps + 120.0, sitl)
    flight["gnss_off_at"] = time.time()
    for name, value in gnss_denial(scenario, config, home).items():
        gcs.set_param(name, value)
    if scenario.output in EXTNAV_OUTPUTS and scenario.gnss == "off":
        gcs.command(dialect().MAV_CMD_SET_EKF_SOURCE_SET, 2)
    deadline = time.monotonic() + config.timeout_s
    over = lambda: _flight_over(track, scenario, config, home)  # noqa: E731
    while not over() and time.monotonic() < deadline and sitl.poll() is None:
        fault.in_flight(gcs, flight)
        select_flow(gcs, scenario, flight)
        time.sleep(0.5)
    flight["ended_at"] = time.time()


def _flight_over(track: Track, scenario: SitlScenario, config: SitlConfig, home: tuple[float, float]) -> bool:
    """A copter lands and disarms; a plane has loitered over home for ``plane_home_s``."""
    if scenario.vehicle != "plane":
        return track.disarmed_at is not None
    arrived = home_arrival(track, config, home)
    return arrived is not None and time.time() - arrived >= config.plane_home_s


def home_arrival(track: Track, config: SitlConfig, home: tuple[float, float]) -> float | None:
    """When a returning plane (RTL) first came onto its loiter over home (within 1.1 radii)."""
    rtl = [t for t, mode in track.modes if mode == PLANE_RTL]
    truth = np.asarray(track.truth, float).reshape(-1, 3)
    truth = truth[truth[:, 0] >= rtl[0]] if rtl else truth[:0]
    near = np.hypot(*LocalFrame(*home).to_enu(truth[:, 1], truth[:, 2])) <= 1.1 * config.loiter_radius_m
    return float(truth[np.argmax(near), 0]) if near.any() else None


def gnss_denial(scenario: SitlScenario, config: SitlConfig, home: tuple[float, float]) -> dict[str, float]:
    """The SITL parameters that take GPS 1 away, or move it by ``config.spoof_m`` (SITL adds
    SIM_GPS_GLITCH to the receiver's latitude and longitude in degrees)."""
    if scenario.gnss == "off":
        return {"SIM_GPS_DISABLE": 1}
    lat, lon = _offset(home, *config.spoof_m)
    return {"SIM_GPS_GLITCH_X": lat - home[0], "SIM_GPS_GLITCH_Y": lon - home[1]}


def _arm_when_ready(gcs: GroundStation, sitl: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """Arming is refused until every pre-arm check passes (the EKF settling): try until then."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            gcs.arm()
            return
        except OrthonavError as error:
            if time.monotonic() > deadline or sitl.poll() is not None:
                prearm = [text for _, text in gcs.track.texts if text.startswith("PreArm")]
                raise OrthonavError(
                    f"{error}; the autopilot said: {prearm[-1] if prearm else 'nothing'}"
                ) from None
            time.sleep(2.0)


def select_flow(gcs: GroundStation, scenario: SitlScenario, flight: dict) -> None:
    """Source set 2 (the flow's velocity) once the copter is below FLOW_SWITCH_M, the time noted."""
    if scenario.flow and "flow_from" not in flight and _rel_alt(gcs) < FLOW_SWITCH_M:
        gcs.command(dialect().MAV_CMD_SET_EKF_SOURCE_SET, 2)
        flight["flow_from"] = time.time()


def _rel_alt(gcs: GroundStation) -> float:
    position = gcs.latest.get("GLOBAL_POSITION_INT")
    return position.relative_alt / 1000.0 if position is not None else 0.0


# --- grading ---------------------------------------------------------------------------------


def grade(
    scenario: SitlScenario,
    config: SitlConfig,
    track: Track,
    flight: dict,
    home: tuple[float, float],
    root: Path,
    frames: int,
) -> dict:
    """The row ``bench sitl`` writes: the issue's fields plus what explains them."""
    off_at, ended = flight.get("gnss_off_at"), flight.get("ended_at", time.time())
    back_at = min(ended, flight.get("gnss_back_at") or math.inf)  # a fault flight may give GNSS back
    est = np.asarray(track.estimate, float).reshape(-1, 4)
    off = est[(est[:, 0] >= off_at) & (est[:, 0] < back_at)] if off_at is not None else est[:0]
    errors = off[:, 3]
    landing_error = return_error(scenario, config, track, home, ended)
    modes = [mode for _, mode in track.modes]
    after_arm = [(t, text) for t, text in track.texts if track.armed_at is not None and t >= track.armed_at]
    failsafes = [text for _, text in after_arm if TROUBLE.search(text)]
    completed = (
        landing_error is not None
        and COPTER_LAND not in modes
        and not any(EKF_FAILSAFE.search(t) for t in failsafes)
    )
    row = {
        "name": scenario.name,
        "vehicle": scenario.vehicle,
        "orthonav": scenario.orthonav,
        "gnss": scenario.gnss,
        "completed": bool(completed),
        "gnss_off_s": round(back_at - off_at, 1) if off_at is not None else 0.0,
        "horizontal_error_p50_m": _pct(errors, 50),
        "horizontal_error_p95_m": _pct(errors, 95),
        "horizontal_error_max_m": _pct(errors, 100),
        "landing_error_m": None if landing_error is None else round(landing_error, 2),
        "failsafes": failsafes,
        "modes": modes,
        "frames": frames,
        "tilt_error_deg": tilt_errors(track, off_at, back_at),
        "parameters": vehicle_params(config, scenario),
        "orthonav_messages": _orthonav(root / "fly" / "companion.jsonl", track, off_at)
        if scenario.orthonav
        else None,
        "localization": (
            localization_pace(root / "fly" / "summary.json", config) if scenario.orthonav else None
        ),
    }
    if scenario.gnss == "spoofed":
        row |= spoof_verdict(off, track, gnss_denial(scenario, config, home))
    row["targets_met"] = targets_met(row) if targets_apply(scenario, flight) else None
    return row


def tilt_errors(track: Track, off_at: float | None, back_at: float) -> dict | None:
    """How far the autopilot's roll and pitch (ATTITUDE) were from SIMSTATE's from arming on
    (before, an EKF may not have aligned its tilt yet), the larger of the two per sample (deg),
    its quantiles with GNSS and without (None for a part without samples): a body-fixed
    camera's fixes are placed with them."""
    if not track.attitude or not track.true_attitude or track.armed_at is None:
        return None
    estimate, truth = np.asarray(track.attitude, float), np.asarray(track.true_attitude, float)
    start, end = max(truth[0, 0], track.armed_at), truth[-1, 0]  # armed, with the truth on both sides
    estimate = estimate[(estimate[:, 0] >= start) & (estimate[:, 0] <= end)]
    true_at = [np.interp(estimate[:, 0], truth[:, 0], truth[:, axis]) for axis in (1, 2)]
    error = np.maximum(
        *(np.abs(estimate[:, axis] - true) for axis, true in zip((1, 2), true_at, strict=True))
    )
    times = estimate[:, 0]
    without = (times >= off_at) & (times < back_at) if off_at is not None else np.zeros(len(times), bool)
    return {
        name: quantiles(error[part], digits=2) for name, part in (("gnss", ~without), ("gnss_off", without))
    }


def return_error(
    scenario: SitlScenario, config: SitlConfig, track: Track, home: tuple[float, float], ended: float
) -> float | None:
    """How far from home the flight ended: a copter's landing point; for a plane, which does not
    land, the centre of its loiter over home (the circle around its true track from its arrival
    there). None where it did not get there (no landing, or less than half of ``plane_home_s``
    loitering over home)."""
    if scenario.vehicle != "plane":
        if track.disarmed_at is None:
            return None
        lat, lon = track.truth_at(np.array([track.disarmed_at]))
        return float(distance_m(*home, float(lat[0]), float(lon[0])))
    arrived = home_arrival(track, config, home)
    if arrived is None or ended - arrived < 0.5 * config.plane_home_s:
        return None
    east, north = LocalFrame(*home).to_enu(*track.truth_at(np.linspace(arrived, ended, 200)))
    (centre_east, centre_north), _ = cv2.minEnclosingCircle(np.column_stack([east, north]).astype(np.float32))
    return float(math.hypot(centre_east, centre_north))


def spoof_verdict(estimates: np.ndarray, track: Track, glitch: dict[str, float]) -> dict:
    """Whom the autopilot believed while GPS 1 was moved: the share of its positions nearer the
    spoofed place (the truth moved by the glitch) than the truth, and its distance from each."""
    if not estimates.size:
        return {"spoof_m": None, "followed_spoofer_share": None, "spoofer_distance_p50_m": None}
    true_lat, true_lon = track.truth_at(estimates[:, 0])
    spoofed_lat, spoofed_lon = true_lat + glitch["SIM_GPS_GLITCH_X"], true_lon + glitch["SIM_GPS_GLITCH_Y"]
    to_spoofer = np.asarray(distance_m(spoofed_lat, spoofed_lon, estimates[:, 1], estimates[:, 2]), float)
    return {
        "spoof_m": round(float(distance_m(true_lat[0], true_lon[0], spoofed_lat[0], spoofed_lon[0])), 1),
        "followed_spoofer_share": round(float(np.mean(to_spoofer < estimates[:, 3])), 3),
        "spoofer_distance_p50_m": _pct(to_spoofer, 50),
    }


def targets_apply(scenario: SitlScenario, flight: dict) -> bool:
    """The copter targets judge a copter that lost GNSS for the rest of its flight: a plane, a
    spoofed GPS 1 or a fault flight that gives GNSS back before the landing gets no verdict."""
    return scenario.vehicle == "copter" and scenario.gnss == "off" and flight.get("gnss_back_at") is None


def targets_met(row: dict) -> bool:
    """The copter targets: mission done, landed within 10 m, p95 <= 10 m, never > 25 m, no EKF failsafe."""
    return bool(
        row["completed"]
        and row["landing_error_m"] is not None
        and row["landing_error_m"] <= 10.0
        and (row["horizontal_error_p95_m"] or math.inf) <= 10.0
        and (row["horizontal_error_max_m"] or math.inf) <= 25.0
    )


def _orthonav(log: Path, track: Track, gnss_off_at: float | None) -> dict | None:
    """What ``fly`` sent: how many, their spacing, and their error against the true track; the
    wrong ones in all and those sent once GNSS was off (before, EKF3 still had GPS 1); how long
    after the GNSS loss or spoof its answer to spoofing (``--on-spoofing``) went out and was accepted."""
    if not log.exists() or not track.truth:
        return None
    records = [json.loads(line) for line in log.read_text().splitlines()]
    sent = [r for r in records if r.get("kind") == "sent"]
    if not sent:
        return {"sent": 0}
    events = [(r["time_s"], r["text"]) for r in records if r.get("kind") == "event"]
    answered = {
        key: next((round(t - gnss_off_at, 1) for t, text in events if pattern.search(text)), None)
        if gnss_off_at is not None
        else None
        for key, pattern in SPOOFING_ANSWER.items()
    }
    times = np.array([r["time_s"] for r in sent])
    state_t = np.array([r["state"]["time_s"] for r in sent])
    # The state each message was made of: the same for every output (GPS_INPUT's accuracy is its sigma).
    lat, lon, sigma = (np.array([r["state"][key] for r in sent]) for key in ("lat", "lon", "sigma_m"))
    true_lat, true_lon = track.truth_at(state_t)
    error = np.asarray(distance_m(true_lat, true_lon, lat, lon), float)
    wrong = (error > WRONG_SIGMAS * sigma) | (error > WRONG_M)
    gaps = np.diff(times)
    return {
        "sent": len(sent),
        "rate_hz": round(float(len(sent) / max(times[-1] - times[0], 1e-9)), 2),
        "gap_p50_s": _pct(gaps, 50),
        "gap_max_s": _pct(gaps, 100),
        "gaps_over_245ms": int((gaps > 0.245).sum()),
        "error_p50_m": _pct(error, 50),
        "error_p95_m": _pct(error, 95),
        "error_max_m": _pct(error, 100),
        "wrong": int(wrong.sum()),
        "wrong_gnss_off": int(wrong[times >= (gnss_off_at or math.inf)].sum()),
        **answered,
        "track": [
            [round(float(t), 2), round(float(a), 7), round(float(b), 7)]
            for t, a, b in zip(times, lat, lon, strict=True)
        ],
    }


def localization_pace(summary: Path, config: SitlConfig) -> dict | None:
    """Did localization keep up with the camera in real time? Behind where more than a tenth of
    the frames were dropped (the worker still busy with an older one) or the p95 capture-to-message
    latency exceeds a frame period."""
    if not summary.exists():
        return None
    fly = json.loads(summary.read_text())
    frames, dropped, p95_ms = (
        fly.get("frames") or 0,
        fly.get("frames_dropped") or 0,
        fly.get("latency_p95_ms"),
    )
    behind = dropped > 0.1 * frames or (p95_ms is not None and p95_ms > 1000.0 / config.frame_rate_hz)
    return {
        "frames": frames,
        "frames_dropped": dropped,
        "latency_median_ms": fly.get("latency_median_ms"),
        "latency_p95_ms": p95_ms,
        "behind_real_time": bool(behind),
    }


def _pct(values: np.ndarray, q: float) -> float | None:
    values = np.asarray(values, float)
    return round(float(np.percentile(values, q)), 2) if values.size else None


# --- the benchmark ---------------------------------------------------------------------------


def run_sitl_benchmark(
    sitl_dir: Path, package: Path, frames_from: Path, out: Path, config: SitlConfig
) -> dict:
    """Every scenario in turn (each is real time), graded; JSON and PNG written to ``out``."""
    # SITL and fly run in the flight's own folder: relative paths would name other files there.
    sitl_dir, package, frames_from, out = (p.resolve() for p in (sitl_dir, package, frames_from, out))
    runs = out.with_suffix("")
    watch = LoadWatch()
    rows = []
    with tqdm(total=len(config.scenarios), desc="SITL flights", unit="flight") as bar:
        for name in config.scenarios:
            row = run_scenario(SCENARIOS[name], config, sitl_dir, package, frames_from, runs / name)
            rows.append(row)
            bar.set_postfix_str(f"{name}: {'done' if row['completed'] else 'not completed'}")
            bar.update()
    result = {
        "config": asdict(config),
        "sitl": sitl_binaries(sitl_dir),
        "map": str(package),
        "frames_from": str(frames_from),
        "machine": watch.record(),
        "rows": rows,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out, result)
    from orthonav.viz.sitl import plot_sitl_bench

    plot_sitl_bench(result, runs, out.with_suffix(".png"), machine_line(result["machine"]))
    return result


def sitl_binaries(sitl_dir: Path) -> dict:
    """Which firmware flew: the folder and each binary's hash."""
    binaries = {vehicle: _sha256(sitl_dir / f"ardu{vehicle}") for vehicle in ("copter", "plane")}
    return {"dir": str(sitl_dir), "binaries": binaries}


def _sha256(path: Path) -> str | None:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16] if path.is_file() else None


def summary_line(result: dict) -> str:
    parts = []
    for row in result["rows"]:
        p95 = row["horizontal_error_p95_m"]
        parts.append(
            f"{row['name']}: {'completed' if row['completed'] else 'NOT completed'}, "
            f"p95 {p95 if p95 is not None else '-'} m, landed {row['landing_error_m']} m from plan"
        )
    return "bench sitl: " + "; ".join(parts)
