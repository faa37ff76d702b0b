"""MAVLink messages carrying a navigation state to the autopilot.

- GPS_INPUT (#232, https://mavlink.io/en/messages/common.html#GPS_INPUT): ArduPilot with
  ``GPS1_TYPE=14`` treats it as a GPS receiver. Its ``time_week``/``time_week_ms`` go through
  ArduPilot's offboard jitter correction (AP_GPS_MAV), so stamping them with the frame's
  capture time lets the EKF place a late fix at the time it was true.
- VISION_POSITION_ESTIMATE (#102, .../common.html#VISION_POSITION_ESTIMATE) and ODOMETRY
  (#331, .../common.html#ODOMETRY): ArduPilot ExternalNav (``VISO_TYPE=1``) and PX4 (EKF2 external
  vision); positions are NED metres from the autopilot's EKF origin, covariances the upper
  triangle of the 6x6 pose matrix, row-major, 21 floats, NaN first when unknown.
- GLOBAL_POSITION_SENSOR (#296, .../common.html#GLOBAL_POSITION_SENSOR): the position measured
  by a global position sensor, here a vision (map-matching) one; PX4 publishes it as its uORB
  ``aux_global_position`` and EKF2 fuses it as an auxiliary global position (``EKF2_AGP*``).
  ``time_usec`` is when the message is sent and ``processing_time`` how long before that the
  position was true, as MAVLink defines them; unknown floats are NaN, MAVLink's "invalid".
- MAV_CMD_EXTERNAL_POSITION_ESTIMATE (43003, .../common.html#MAV_CMD_EXTERNAL_POSITION_ESTIMATE)
  in a COMMAND_INT: ArduPilot (4.5+) sets EKF3's horizontal position and its variance to it, but
  only while EKF3 dead-reckons (no position source passing its checks): the way to put it back
  on the map when fixes resume after a span without any, instead of waiting for a GPS it has
  dropped to be detected again.
- MAV_CMD_SET_EKF_SOURCE_SET (42007, ArduPilot's ardupilotmega.xml) in a COMMAND_LONG: param1 the
  source set, 1-3 (``EK3_SRC1_*`` to ``EK3_SRC3_*``), answered by a COMMAND_ACK; the same selection
  an RC switch (``RCx_OPTION 90``) makes.

Only a trusted state can become a message: the builders raise on any other, so an untrusted
position cannot reach the autopilot by mistake.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from typing import TYPE_CHECKING, Any

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.geo import LocalFrame
from orthonav.mavlink.link import dialect

if TYPE_CHECKING:
    from orthonav.fusion import NavState
    from orthonav.types import Fix

TRUSTED_STATUSES = ("fixed", "dead reckoning")
GPS_EPOCH_UNIX_S = 315964800  # 1980-01-06T00:00:00Z
GPS_LEAP_S = 18  # GPS - UTC since 2017-01-01
WEEK_MS = 7 * 86400 * 1000
FIX_3D = 3
SATELLITES = 10
UERE_M = 5.0  # typical single-frequency range error: DOP = accuracy / UERE
MIN_DOP = 0.5
MIN_SPEED_SIGMA_MPS = 1.0
VELOCITY_BASELINE_S = 1.0
UNKNOWN_SPEED_SIGMA_MPS = 50.0  # the most EKF3 takes as a GPS speed accuracy: "no velocity"
# A ground velocity measured from the frames counts while its time (the middle of its frame pair)
# is this recent: half a frame period plus the localization's latency, with room for one refusal.
MEASURED_VELOCITY_S = 1.5
MIN_MEASURED_SPEED_SIGMA_MPS = 0.3  # EKF3's own floor for a GPS speed accuracy (EK3_VELNE_M_NSE)
# PX4 binds a GLOBAL_POSITION_SENSOR to an EKF2 slot by this id (EKF2_AGPn_ID; 0 disables a
# slot, so 0 cannot be used); its uORB message reserves 1X for visual navigation.
SENSOR_ID = 10
MAX_UINT32 = 2**32 - 1
# MAV_CMD_EXTERNAL_POSITION_ESTIMATE's send time is a float32 that the sender wraps; the
# definition asks for a wrap of at most 250 s (about 10 microseconds of resolution).
EXTERNAL_ESTIMATE_WRAP_S = 250.0
EKF_SOURCE_SETS = (1, 2, 3)  # EK3_SRC1_* to EK3_SRC3_*


def gps_time(unix_s: float) -> tuple[int, int]:
    """(GPS week, milliseconds into the week) of a UNIX time (GPS = UTC + 18 leap seconds)."""
    gps_ms = round((unix_s - GPS_EPOCH_UNIX_S + GPS_LEAP_S) * 1000.0)
    week, week_ms = divmod(gps_ms, WEEK_MS)
    return int(week), int(week_ms)


def withheld_because(state: NavState, max_sigma_m: float, max_reckoning_s: float) -> str:
    """Why the filter's ``state`` must not go out; empty when it may. The filter's part of what
    ``fly`` checks, which ``replay`` checks again on its re-run.

    Beyond ``max_reckoning_s`` since the last fix, a position is sent only while a ground velocity
    measured from the frames is fresh: then it is carried by orthonav's own visual odometry, not
    by the autopilot's velocity handed back to it, and its sigma (bounded by ``max_sigma_m``)
    grows with that velocity's."""
    if state.status not in TRUSTED_STATUSES:
        return f"navigation {state.status}"
    if state.sigma_m > max_sigma_m:
        return f"uncertainty {state.sigma_m:.0f} m > {max_sigma_m:.0f} m"
    if state.since_fix_s is None:
        return "no visual fix yet: the autopilot navigates on its own"
    if state.since_fix_s > max_reckoning_s and not velocity_measured(state):
        return f"no visual fix for {state.since_fix_s:.0f} s: the autopilot dead-reckons on its own"
    return ""


def velocity_measured(state: NavState) -> bool:
    """Whether the state's velocity is the ground's, measured from the frames within
    ``MEASURED_VELOCITY_S``, rather than the autopilot's own."""
    since = state.since_velocity_s
    return since is not None and since <= MEASURED_VELOCITY_S and math.isfinite(state.velocity_sigma_mps)


def check_trusted(state: NavState, what: str) -> None:
    """Raise unless ``state`` may be sent: a trusted status and a finite covariance."""
    if state.status not in TRUSTED_STATUSES:
        raise OrthonavError(f"{what}: refusing to send a navigation state that is {state.status!r}")
    if not np.all(np.isfinite(state.covariance_enu_m2)) or not math.isfinite(state.heading_sigma_deg):
        raise OrthonavError(f"{what}: refusing to send a navigation state without a finite covariance")


def gps_input(
    state: NavState,
    capture_unix_s: float,
    alt_msl_m: float | None,
    vert_sigma_m: float = 10.0,
    send_yaw: bool = False,
    gps_id: int = 0,
) -> Any:
    """GPS_INPUT with a 3-D fix: accuracies from the covariance, DOPs derived from them.

    Horizontal velocity is always filled: ArduPilot takes a GPS_INPUT without it as zero
    velocity. Without ``alt_msl_m`` the altitude fields are flagged as ignored (ArduPilot then
    reads 0 m: keep the EKF height source on the barometer). ``send_yaw`` sends the heading,
    which ArduPilot treats as a GPS yaw (EK3_SRC1_YAW=2/3); 0 would mean unknown, north is 36000.
    The speed accuracy is :func:`speed_sigma_mps`'s.
    """
    check_trusted(state, "GPS_INPUT")
    mavlink = dialect()
    ignore = mavlink.GPS_INPUT_IGNORE_FLAG_VEL_VERT
    if alt_msl_m is None:
        ignore |= (
            mavlink.GPS_INPUT_IGNORE_FLAG_ALT
            | mavlink.GPS_INPUT_IGNORE_FLAG_VDOP
            | mavlink.GPS_INPUT_IGNORE_FLAG_VERTICAL_ACCURACY
        )
    horiz_m = float(state.sigma_m)
    week, week_ms = gps_time(capture_unix_s)
    return mavlink.MAVLink_gps_input_message(
        time_usec=_usec(capture_unix_s),
        gps_id=gps_id,
        ignore_flags=ignore,
        time_week_ms=week_ms,
        time_week=week,
        fix_type=FIX_3D,
        lat=round(state.lat * 1e7),
        lon=round(state.lon * 1e7),
        alt=float(alt_msl_m or 0.0),
        hdop=_dop(horiz_m),
        vdop=_dop(vert_sigma_m),
        vn=float(state.vel_north_mps),
        ve=float(state.vel_east_mps),
        vd=0.0,
        speed_accuracy=speed_sigma_mps(state),
        horiz_accuracy=horiz_m,
        vert_accuracy=float(vert_sigma_m),
        satellites_visible=SATELLITES,
        yaw=_yaw_cdeg(state.heading_deg) if send_yaw else 0,
    )


def global_position_sensor(
    state: NavState,
    capture_unix_s: float,
    alt_msl_m: float | None,
    sent_unix_s: float | None = None,
    vert_sigma_m: float = 10.0,
    sensor_id: int = SENSOR_ID,
    target: tuple[int, int] = (0, 0),
) -> Any:
    """GLOBAL_POSITION_SENSOR from a vision source: ``eph`` the worst horizontal 1-sigma.

    ``capture_unix_s`` is when the state was true and ``sent_unix_s`` when it goes out (default:
    now); their difference is the ``processing_time`` a receiver can use to place the fix in
    time. Without ``alt_msl_m`` the altitude and ``epv`` are NaN (unknown), never 0 m. The flags
    stay 0: a state that is sent is healthy, and it is not the autopilot's primary estimate.
    """
    check_trusted(state, "GLOBAL_POSITION_SENSOR")
    mavlink = dialect()
    sent_s = time.time() if sent_unix_s is None else sent_unix_s
    has_alt = alt_msl_m is not None
    return mavlink.MAVLink_global_position_sensor_message(
        target_system=target[0],
        target_component=target[1],
        id=sensor_id,
        time_usec=_usec(sent_s),
        processing_time=min(max(_usec(sent_s - capture_unix_s), 0), MAX_UINT32),
        source=mavlink.GLOBAL_POSITION_SRC_VISION,
        flags=0,
        lat=round(state.lat * 1e7),
        lon=round(state.lon * 1e7),
        alt_ellipsoid=math.nan,  # the geoid separation is not known here
        alt=float(alt_msl_m) if has_alt else math.nan,
        eph=float(state.sigma_m),
        epv=float(vert_sigma_m) if has_alt else math.nan,
    )


def external_position_estimate(
    fix: Fix, capture_unix_s: float, sent_unix_s: float | None = None, target: tuple[int, int] = (0, 0)
) -> Any:
    """MAV_CMD_EXTERNAL_POSITION_ESTIMATE (COMMAND_INT, MAV_FRAME_GLOBAL) of an accepted fix:
    param1 the send time (wrapped), param2 how long before it the frame was captured, param3
    the fix's 1-sigma; the altitude is NaN, which the definition asks for (not used)."""
    if not fix.accepted or fix.pose is None or fix.sigma_m is None:
        raise OrthonavError(f"MAV_CMD_EXTERNAL_POSITION_ESTIMATE: an accepted fix expected ({fix.reason})")
    mavlink = dialect()
    sent_s = time.time() if sent_unix_s is None else sent_unix_s
    return mavlink.MAVLink_command_int_message(
        target[0],
        target[1],
        mavlink.MAV_FRAME_GLOBAL,
        mavlink.MAV_CMD_EXTERNAL_POSITION_ESTIMATE,
        0,
        0,
        float(sent_s % EXTERNAL_ESTIMATE_WRAP_S),
        float(max(sent_s - capture_unix_s, 0.0)),
        float(fix.sigma_m),
        math.nan,
        round(fix.pose.lat * 1e7),
        round(fix.pose.lon * 1e7),
        math.nan,
    )


def param_set_int(target: tuple[int, int], name: str, value: int) -> Any:
    """PARAM_SET of an integer parameter (ArduPilot takes its value as the float field)."""
    mavlink = dialect()
    return mavlink.MAVLink_param_set_message(
        target[0], target[1], name.encode("ascii"), float(value), mavlink.MAV_PARAM_TYPE_INT8
    )


def set_ekf_source_set(target: tuple[int, int], source_set: int) -> Any:
    """MAV_CMD_SET_EKF_SOURCE_SET: EKF3 takes its position, velocity and yaw from ``source_set``."""
    if source_set not in EKF_SOURCE_SETS:
        raise OrthonavError(f"MAV_CMD_SET_EKF_SOURCE_SET: source set {source_set}, expected 1, 2 or 3")
    mavlink = dialect()
    return mavlink.MAVLink_command_long_message(
        target[0], target[1], mavlink.MAV_CMD_SET_EKF_SOURCE_SET, 0, float(source_set), 0, 0, 0, 0, 0, 0
    )


def request_message(target: tuple[int, int], message_id: int) -> Any:
    """MAV_CMD_REQUEST_MESSAGE for one message the autopilot sends only when something changes
    (GPS_GLOBAL_ORIGIN: once, when its EKF sets the origin)."""
    mavlink = dialect()
    return mavlink.MAVLink_command_long_message(
        target[0], target[1], mavlink.MAV_CMD_REQUEST_MESSAGE, 0, float(message_id), 0, 0, 0, 0, 0, 0
    )


def speed_sigma_mps(state: NavState) -> float:
    """The accuracy GPS_INPUT claims for its velocity: the filter's velocity sigma while a ground
    velocity measured from the frames is fresh; otherwise what two of our positions a second apart
    can tell of it, and nothing (EKF3's ceiling) once the last fix is older than that.

    Between fixes and without measured velocities the velocity is the autopilot's own, fed back
    late. Claimed at a GPS's accuracy, EKF3 fuses its own delayed velocity: in ArduPilot SITL its
    heading drifted while the copter accelerated, and without fixes its velocity ran away by metres
    per second within seconds. A measured velocity is the ground's, independent of the autopilot."""
    if velocity_measured(state):
        return min(max(MIN_MEASURED_SPEED_SIGMA_MPS, state.velocity_sigma_mps), UNKNOWN_SPEED_SIGMA_MPS)
    if state.since_fix_s is None or state.since_fix_s > VELOCITY_BASELINE_S:
        return UNKNOWN_SPEED_SIGMA_MPS
    return max(MIN_SPEED_SIGMA_MPS, math.sqrt(2.0) * float(state.sigma_m) / VELOCITY_BASELINE_S)


@dataclass(frozen=True)
class PoseExtras:
    """What the external-navigation messages carry besides the horizontal state.

    ``up_m`` is the height above the origin (default: the state's height above ground);
    pitch and roll are the vehicle's, from its telemetry.
    """

    up_m: float | None = None
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    vert_sigma_m: float = 10.0
    tilt_sigma_deg: float = 2.0
    reset_counter: int = 0


def vision_position_estimate(
    state: NavState, origin: tuple[float, float], capture_unix_s: float, extras: PoseExtras = PoseExtras()
) -> Any:
    """VISION_POSITION_ESTIMATE: NED metres from ``origin`` (lat, lon), attitude in radians."""
    check_trusted(state, "VISION_POSITION_ESTIMATE")
    north, east, down = _ned(state, origin, extras.up_m)
    return dialect().MAVLink_vision_position_estimate_message(
        usec=_usec(capture_unix_s),
        x=north,
        y=east,
        z=down,
        roll=math.radians(extras.roll_deg),
        pitch=math.radians(extras.pitch_deg),
        yaw=_yaw_rad(state.heading_deg),
        covariance=pose_covariance(state, extras),
        reset_counter=extras.reset_counter,
    )


def odometry(
    state: NavState, origin: tuple[float, float], capture_unix_s: float, extras: PoseExtras = PoseExtras()
) -> Any:
    """ODOMETRY in the frames ArduPilot requires and PX4 accepts: pose MAV_FRAME_LOCAL_FRD (NED
    axes at ``origin``), velocity MAV_FRAME_BODY_FRD; angular rates and velocity covariance
    are unknown (NaN)."""
    check_trusted(state, "ODOMETRY")
    mavlink = dialect()
    north, east, down = _ned(state, origin, extras.up_m)
    yaw = math.radians(state.heading_deg)
    forward = state.vel_north_mps * math.cos(yaw) + state.vel_east_mps * math.sin(yaw)
    right = -state.vel_north_mps * math.sin(yaw) + state.vel_east_mps * math.cos(yaw)
    return mavlink.MAVLink_odometry_message(
        time_usec=_usec(capture_unix_s),
        frame_id=mavlink.MAV_FRAME_LOCAL_FRD,
        child_frame_id=mavlink.MAV_FRAME_BODY_FRD,
        x=north,
        y=east,
        z=down,
        q=quaternion_wxyz(extras.roll_deg, extras.pitch_deg, state.heading_deg),
        vx=float(forward),
        vy=float(right),
        vz=0.0,
        rollspeed=math.nan,
        pitchspeed=math.nan,
        yawspeed=math.nan,
        pose_covariance=pose_covariance(state, extras),
        velocity_covariance=upper_triangle(np.full((6, 6), np.nan)),
        reset_counter=extras.reset_counter,
        estimator_type=mavlink.MAV_ESTIMATOR_TYPE_VISION,
        quality=0,
    )


def pose_covariance(state: NavState, extras: PoseExtras) -> list[float]:
    """The 6x6 (x, y, z, roll, pitch, yaw) covariance of a state, NED metres and radians."""
    (ee, en), (_, nn) = np.asarray(state.covariance_enu_m2, float)
    cov = np.zeros((6, 6))
    cov[:2, :2] = [[nn, en], [en, ee]]
    cov[2, 2] = extras.vert_sigma_m**2
    cov[3, 3] = cov[4, 4] = math.radians(extras.tilt_sigma_deg) ** 2
    cov[5, 5] = math.radians(state.heading_sigma_deg) ** 2
    return upper_triangle(cov)


def upper_triangle(cov: np.ndarray) -> list[float]:
    """MAVLink's 21-float layout: row-major upper triangle; NaN first when anything is unknown."""
    values = [float(v) for v in np.asarray(cov, float)[np.triu_indices(6)]]
    if not all(math.isfinite(v) for v in values):
        return [math.nan] + [0.0] * 20
    return values


def quaternion_wxyz(roll_deg: float, pitch_deg: float, yaw_deg: float) -> list[float]:
    """Body -> NED rotation (aerospace ZYX Euler angles) as (w, x, y, z)."""
    r, p, y = (math.radians(a) / 2.0 for a in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return [
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ]


def _ned(state: NavState, origin: tuple[float, float], up_m: float | None) -> tuple[float, float, float]:
    east, north = _frame(*origin).to_enu(state.lat, state.lon)
    up = up_m if up_m is not None else (state.alt_agl_m or 0.0)
    return float(north), float(east), -float(up)


@lru_cache(maxsize=8)
def _frame(lat: float, lon: float) -> LocalFrame:
    """The origin's frame, built once (a projection is costly to build, and the origin rarely changes)."""
    return LocalFrame(lat, lon)


def _usec(unix_s: float) -> int:
    return round(unix_s * 1e6)


def _dop(accuracy_m: float) -> float:
    return max(MIN_DOP, float(accuracy_m) / UERE_M)


def _yaw_cdeg(heading_deg: float) -> int:
    """Centidegrees in 1..36000: 0 means 'unknown' in GPS_INPUT, so north is 36000."""
    return round(heading_deg % 360.0 * 100.0) or 36000


def _yaw_rad(heading_deg: float) -> float:
    return math.radians((heading_deg + 180.0) % 360.0 - 180.0)
