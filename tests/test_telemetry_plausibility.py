"""The autopilot's velocity judged before it is dead-reckoned: synthetic MAVLink streams.

A scripted autopilot flies east at 20 m/s and sends, every 0.1 s, GLOBAL_POSITION_INT (its
position as flown), LOCAL_POSITION_NED and ATTITUDE; a fault rewrites the velocities it reports.
No message goes over a socket: each is packed and parsed as pymavlink receives it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from orthonav.errors import OrthonavError
from orthonav.fusion import FilterConfig, ImuErrorModel, InsSample, NavFilter
from orthonav.geo import destination, distance_m
from orthonav.mavlink.companion import CompanionConfig, TelemetryToFilter
from orthonav.mavlink.link import dialect
from orthonav.mavlink.plausibility import HOLD_SIGMAS, VEHICLE_CLASSES, Plausibility
from orthonav.mavlink.telemetry import Telemetry
from orthonav.types import Fix, Pose

LAT, LON = 47.02, -99.15
SPEED_MPS = 20.0
PERIOD_S = 0.1
ARRIVAL_OFFSET_S = 1_000_000.0  # companion UNIX time minus autopilot boot time
COPTER = VEHICLE_CLASSES["copter"]

# A fault: (message type, boot time, true (east, north) velocity) -> the (east, north) it reports.
Fault = Callable[[str, float, tuple[float, float]], tuple[float, float]]


def as_received(msg: Any) -> Any:
    mavlink = dialect()
    return mavlink.MAVLink(None).parse_buffer(msg.pack(mavlink.MAVLink(None, 1, 1)))[0]


class ScriptedAutopilot:
    """East at ``speed_mps``; positions as flown, velocities through ``fault``."""

    def __init__(self, fault: Fault | None = None, speed_mps: float = SPEED_MPS, mav_type: int = 2) -> None:
        self.fault = fault or (lambda kind, t, v: v)
        self.speed_mps, self.mav_type = speed_mps, mav_type

    def position(self, boot_s: float) -> tuple[float, float]:
        return destination(LAT, LON, 90.0, self.speed_mps * boot_s)

    def messages(self, boot_s: float) -> list[Any]:
        mavlink, ms = dialect(), round(boot_s * 1000)
        lat, lon = self.position(boot_s)
        true_velocity = (self.speed_mps, 0.0)
        g_east, g_north = self.fault("GLOBAL_POSITION_INT", boot_s, true_velocity)
        l_east, l_north = self.fault("LOCAL_POSITION_NED", boot_s, true_velocity)
        cm = [max(-32767, min(32767, round(v * 100))) for v in (g_north, g_east)]
        msgs = [
            mavlink.MAVLink_global_position_int_message(
                ms, round(lat * 1e7), round(lon * 1e7), 1_400_000, 1_000_000, *cm, 0, 9000
            ),
            mavlink.MAVLink_local_position_ned_message(ms, 0.0, 0.0, -1000.0, l_north, l_east, 0.0),
            mavlink.MAVLink_attitude_message(ms, 0.0, 0.0, math.radians(90.0), 0.0, 0.0, 0.0),
        ]
        if ms % 1000 == 0:
            msgs.append(mavlink.MAVLink_heartbeat_message(self.mav_type, 3, 0, 0, 4, 3))
        return [as_received(m) for m in msgs]


def fly(
    autopilot: ScriptedAutopilot, seconds: float, telemetry: Telemetry | None = None
) -> tuple[Telemetry, list[tuple[float, InsSample | None, Any]]]:
    """(boot time, INS sample, verdict) every period."""
    telemetry = telemetry or Telemetry()
    out = []
    for k in range(round(seconds / PERIOD_S) + 1):
        boot_s = k * PERIOD_S
        now = ARRIVAL_OFFSET_S + boot_s
        for msg in autopilot.messages(boot_s):
            telemetry.ingest(msg, now)
        out.append((boot_s, telemetry.ins_sample(now), telemetry.velocity))
    return telemetry, out


def during(start_s: float, end_s: float, velocity: tuple[float, float], kinds: tuple[str, ...]) -> Fault:
    """Report ``velocity`` in messages of ``kinds`` between two boot times."""

    def fault(kind: str, t: float, true: tuple[float, float]) -> tuple[float, float]:
        return velocity if kind in kinds and start_s <= t < end_s - 1e-9 else true

    return fault


BOTH = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED")


def velocity(sample: InsSample) -> tuple[float, float]:
    return sample.vel_east_mps, sample.vel_north_mps


def test_a_local_velocity_beyond_the_vehicle_is_refused_for_the_global_one() -> None:
    fault = during(3.0, 6.0, (350.0, 0.0), ("LOCAL_POSITION_NED",))
    _, rows = fly(ScriptedAutopilot(fault), 8.0)
    for boot_s, sample, verdict in rows:
        assert velocity(sample) == pytest.approx((SPEED_MPS, 0.0), abs=0.01)
        assert sample.velocity_sigma_mps == 0.0 and verdict.rejected is None
        if 3.0 <= boot_s < 6.0:
            assert verdict.note.startswith("LOCAL_POSITION_NED: 350.0 m/s, beyond a copter's 40 m/s")
        else:
            assert verdict.note is None


def test_one_glitch_in_both_sources_is_held_over_and_the_next_sample_taken() -> None:
    fault = during(3.0, 3.0 + PERIOD_S, (1000.0, 0.0), BOTH)
    _, rows = fly(ScriptedAutopilot(fault), 5.0)
    glitched = [(b, s, v) for b, s, v in rows if v.rejected]
    assert [b for b, _, _ in glitched] == [pytest.approx(3.0)]
    _, sample, verdict = glitched[0]
    assert "GLOBAL_POSITION_INT: 327.7 m/s, beyond a copter's 40 m/s" in verdict.rejected
    assert "LOCAL_POSITION_NED: 1000.0 m/s" in verdict.rejected
    assert velocity(sample) == pytest.approx((SPEED_MPS, 0.0), abs=0.01)
    held_s = PERIOD_S
    assert sample.velocity_sigma_mps == pytest.approx(COPTER.max_accel_mps2 / HOLD_SIGMAS * held_s, rel=0.01)
    assert all(s.velocity_sigma_mps == 0.0 for b, s, _ in rows if b > 3.05)


def test_a_bias_within_the_speed_limit_is_rejected_for_as_long_as_it_lasts() -> None:
    """30 m/s too far north in both sources for 6 s: first an acceleration no copter has, then a
    velocity its own positions do not follow. The last plausible one is held, its sigma growing."""
    fault = during(3.0, 9.0, (SPEED_MPS, 30.0), BOTH)
    _, rows = fly(ScriptedAutopilot(fault), 12.0)
    for boot_s, sample, verdict in rows:
        assert velocity(sample) == pytest.approx((SPEED_MPS, 0.0), abs=0.01)
        inside = 3.0 <= boot_s < 8.95
        assert (verdict.rejected is not None) == inside, boot_s
        held_s = boot_s - 2.9 if inside else 0.0
        assert sample.velocity_sigma_mps == pytest.approx(
            COPTER.max_accel_mps2 / HOLD_SIGMAS * held_s, abs=0.01
        )
    reasons = {round(b, 1): v.rejected for b, _, v in rows if v.rejected}
    assert "changed 30.0 m/s in 0.10 s" in reasons[3.0]
    assert "off the autopilot's own track (20.0 m/s over" in reasons[8.0]


def test_a_nan_local_velocity_and_a_global_one_at_its_limit_are_rejected() -> None:
    def fault(kind: str, t: float, true: tuple[float, float]) -> tuple[float, float]:
        if not 3.0 <= t < 6.0:
            return true
        return (math.nan, math.nan) if kind == "LOCAL_POSITION_NED" else (327.0, 0.0)

    _, rows = fly(ScriptedAutopilot(fault), 7.0)
    rejected = [v.rejected for b, _, v in rows if 3.0 <= b < 5.95]
    assert len(rejected) == 30
    assert all("LOCAL_POSITION_NED: velocity not finite" in r and "327.0 m/s" in r for r in rejected)
    assert all(velocity(s) == pytest.approx((SPEED_MPS, 0.0), abs=0.01) for _, s, _ in rows)


class SteppingAutopilot(ScriptedAutopilot):
    """Its position as ``where`` says at each boot time (the flight's true one otherwise): an EKF
    that reports before it has an origin, or resets its position onto another GPS."""

    def __init__(self, where: Callable[[float, tuple[float, float]], tuple[float, float]], **kw: Any) -> None:
        super().__init__(**kw)
        self.where = where

    def position(self, boot_s: float) -> tuple[float, float]:
        return self.where(boot_s, super().position(boot_s))


@pytest.mark.parametrize("step_m", [15.0, 40.0, 120.0])
def test_a_reset_of_the_autopilots_position_is_not_taken_for_speed(step_m: float) -> None:
    """From 3 s on the EKF's position is ``step_m`` north of where it was (a GPS switched): the
    velocities, still right, are all used."""

    def where(boot_s: float, true: tuple[float, float]) -> tuple[float, float]:
        return destination(*true, 0.0, step_m) if boot_s >= 3.0 else true

    _, rows = fly(SteppingAutopilot(where), 8.0)
    assert [b for b, _, v in rows if v.rejected or v.note] == []
    assert all(velocity(s) == pytest.approx((SPEED_MPS, 0.0), abs=0.01) for _, s, _ in rows)


@pytest.mark.parametrize("mav_type", [1, 2])
def test_a_first_report_before_the_ekf_has_its_origin_does_not_anchor_the_track(mav_type: int) -> None:
    """ArduPlane's first positions, before its EKF origin, are near 0 N 0 E; the flight's are
    thousands of kilometres away. Every velocity after them is used."""

    def where(boot_s: float, true: tuple[float, float]) -> tuple[float, float]:
        return (0.0001045, -0.0000079) if boot_s < 0.25 else true

    telemetry, rows = fly(SteppingAutopilot(where, mav_type=mav_type), 6.0)
    assert [b for b, _, v in rows if v is not None and (v.rejected or v.note)] == []
    assert [b for b, s, _ in rows if s is None] == [0.0, 0.1, 0.2]
    assert telemetry.problem is None


def test_a_report_before_the_ekf_origin_is_no_position_and_the_filter_starts_on_the_flight() -> None:
    """ArduPlane's first reports near 0 N 0 E are not positions: the filter fed through them
    starts where the vehicle is, and its estimate stays finite and on the track."""

    def where(boot_s: float, true: tuple[float, float]) -> tuple[float, float]:
        return (0.0001045, -0.0000079) if boot_s < 1.0 else true

    autopilot, telemetry = SteppingAutopilot(where, mav_type=1), Telemetry()
    nav = NavFilter(FilterConfig.for_imu(ImuErrorModel.preset("consumer")))
    to_filter = TelemetryToFilter(telemetry, nav, init_sigma_m=5.0)
    problems, errors = set(), []
    for k in range(round(4.0 / PERIOD_S) + 1):
        boot_s, now = k * PERIOD_S, ARRIVAL_OFFSET_S + k * PERIOD_S
        for msg in autopilot.messages(boot_s):
            telemetry.ingest(msg, now)
        if to_filter.step(now) is None:
            problems.add(telemetry.problem)
        else:
            errors.append(distance_m(nav.state().lat, nav.state().lon, *autopilot.position(boot_s)))
    assert problems == {"GLOBAL_POSITION_INT has no position (at 0 N 0 E: its EKF has no origin yet)"}
    assert len(errors) >= 25 and max(errors) < 1.0


def test_a_bias_is_still_refused_across_a_reset_of_the_position() -> None:
    """A reset does not open the gate: a velocity 30 m/s off that starts with it is refused."""

    def where(boot_s: float, true: tuple[float, float]) -> tuple[float, float]:
        return destination(*true, 0.0, 40.0) if boot_s >= 3.0 else true

    fault = during(3.0, 6.0, (SPEED_MPS, 30.0), BOTH)
    _, rows = fly(SteppingAutopilot(where, fault=fault), 8.0)
    assert all(velocity(s) == pytest.approx((SPEED_MPS, 0.0), abs=0.01) for _, s, _ in rows)
    assert all(v.rejected for b, _, v in rows if 3.0 <= b < 5.95)


def test_a_plane_may_fly_faster_than_a_copter_and_limits_can_be_set() -> None:
    plane = ScriptedAutopilot(speed_mps=60.0, mav_type=1)  # MAV_TYPE_FIXED_WING
    _, rows = fly(plane, 2.0)
    assert all(s is not None and s.vel_east_mps == pytest.approx(60.0) for _, s, _ in rows)
    copter = ScriptedAutopilot(speed_mps=60.0, mav_type=2)  # MAV_TYPE_QUADROTOR
    telemetry, rows = fly(copter, 2.0)
    assert all(s is None for _, s, _ in rows)
    assert telemetry.problem.startswith("no plausible velocity yet (LOCAL_POSITION_NED: 60.0 m/s, beyond")
    _, rows = fly(copter, 2.0, Telemetry(plausibility=Plausibility("copter", max_speed_mps=70.0)))
    assert all(s is not None for _, s, _ in rows)
    assert Plausibility("plane", max_accel_mps2=5.0).limits(None).max_accel_mps2 == 5.0


def test_bad_vehicle_settings_are_refused_with_the_choices() -> None:
    with pytest.raises(OrthonavError, match="vehicle 'boat': expected one of auto, copter, plane"):
        CompanionConfig(vehicle="boat")
    with pytest.raises(OrthonavError, match="copter limits max_accel_mps2: expected a positive number"):
        CompanionConfig(vehicle="copter", max_accel_mps2=-1.0)


def test_dead_reckoning_through_a_bias_never_sends_a_position_beyond_3_sigma_or_50_m() -> None:
    """TelemetryToFilter with fixes of the truth every 0.5 s, through the 30 m/s bias; the
    estimate is judged at every sample against where the vehicle is."""
    fault = during(10.0, 16.0, (SPEED_MPS, 30.0), BOTH)
    autopilot, telemetry = ScriptedAutopilot(fault), Telemetry()
    nav = NavFilter(FilterConfig.for_imu(ImuErrorModel.preset("consumer")))
    to_filter = TelemetryToFilter(telemetry, nav, init_sigma_m=5.0)
    worst = []
    for k in range(round(30.0 / PERIOD_S) + 1):
        boot_s, now = k * PERIOD_S, ARRIVAL_OFFSET_S + k * PERIOD_S
        for msg in autopilot.messages(boot_s):
            telemetry.ingest(msg, now)
        to_filter.step(now)
        if k % 5 == 0:
            nav.update(truth_fix(autopilot.position(boot_s)), now)
        state = nav.state()
        error = distance_m(state.lat, state.lon, *autopilot.position(boot_s))
        worst.append(error / min(50.0, 3.0 * state.sigma_m))
    assert max(worst) < 1.0, int(np.argmax(worst))


def truth_fix(latlon: tuple[float, float]) -> Fix:
    lat, lon = latlon
    pose = Pose(lat, lon, 1000.0, 90.0, 0.0, 0.0, lat, lon)
    return Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * 25.0, method="test")
