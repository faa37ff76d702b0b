"""Before its first visual fix the companion searches around the autopilot's GNSS position.

A plane climbing out sees too little ground to match for a minute; the filter's start sigma
grows meanwhile, and a search that wide can find look-alike places that agree with each other.
While the autopilot's own receiver reports a 3-D fix, the filter is held at the autopilot's
position instead: wrong fixes hundreds of metres off are gated out, right ones start navigation,
and from the first fused fix on the receiver is no longer listened to.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from orthonav.fusion import FilterConfig, NavFilter
from orthonav.geo import destination, distance_m
from orthonav.mavlink.companion import GNSS_SEED_FLOOR_M, TelemetryToFilter
from orthonav.mavlink.link import dialect
from orthonav.mavlink.telemetry import Telemetry
from orthonav.types import Fix, Pose

LAT, LON = 47.02, -99.15
SPEED_MPS, ALT_AGL_M = 25.0, 250.0
BOOT_TO_UNIX_S = 1000.0


def parsed(*messages: Any) -> list[Any]:
    mavlink = dialect()
    codec = mavlink.MAVLink(None, 1, 1)
    return [mavlink.MAVLink(None).parse_buffer(m.pack(codec))[0] for m in messages]


def where(boot_s: float) -> tuple[float, float]:
    """The autopilot's position (its GNSS's while healthy): flying east."""
    return destination(LAT, LON, 90.0, SPEED_MPS * boot_s)


def telemetry_at(boot_s: float, fix_type: int | None) -> list[Any]:
    """GLOBAL_POSITION_INT and ATTITUDE every step; GPS_RAW_INT (first receiver) once a second."""
    mavlink, ms = dialect(), round(boot_s * 1000)
    lat, lon = where(boot_s)
    msgs = [
        mavlink.MAVLink_global_position_int_message(
            ms,
            round(lat * 1e7),
            round(lon * 1e7),
            600_000,
            round(ALT_AGL_M * 1000),
            0,
            round(SPEED_MPS * 100),
            0,
            9000,
        ),
        mavlink.MAVLink_attitude_message(ms, 0.0, 0.0, math.radians(90.0), 0, 0, 0),
    ]
    if fix_type is not None and ms % 1000 == 0:
        msgs.append(
            mavlink.MAVLink_gps_raw_int_message(
                ms * 1000,
                fix_type,
                round(lat * 1e7),
                round(lon * 1e7),
                600_000,
                121,
                200,
                2500,
                9000,
                12,
                h_acc=300,
            )
        )
    return parsed(*msgs)


def fix_at(lat: float, lon: float) -> Fix:
    pose = Pose(lat, lon, ALT_AGL_M, 90.0, 0.0, 0.0, lat, lon)
    return Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * 15.0**2, method="test")


class Flight:
    """Telemetry at 10 Hz into Telemetry -> TelemetryToFilter -> NavFilter, as ``fly`` steps it."""

    def __init__(self, gnss_seed: bool = True) -> None:
        self.telemetry = Telemetry()
        self.nav = NavFilter(FilterConfig())
        self.to_filter = TelemetryToFilter(self.telemetry, self.nav, 100.0, gnss_seed)
        self.boot_s = 0.0

    def fly(self, seconds: float, fix_type: int | None = 3) -> None:
        end = self.boot_s + seconds
        while self.boot_s < end - 1e-9:
            self.boot_s = round(self.boot_s + 0.1, 3)
            now = self.boot_s + BOOT_TO_UNIX_S
            for msg in telemetry_at(self.boot_s, fix_type):
                self.telemetry.ingest(msg, now)
            self.to_filter.step(now)

    def fuse(self, lat: float, lon: float) -> bool:
        """A fix of a frame captured now."""
        return self.nav.update(fix_at(lat, lon), self.boot_s + BOOT_TO_UNIX_S).accepted

    def off_m(self) -> float:
        state = self.nav.state()
        return distance_m(state.lat, state.lon, *where(self.boot_s))


def wrong_place(boot_s: float, off_m: float) -> tuple[float, float]:
    """A look-alike place ``off_m`` north of the vehicle, moving with it (wrong fixes that agree)."""
    return destination(*where(boot_s), 0.0, off_m)


@pytest.mark.parametrize("off_m", [120.0, 240.0, 600.0])
def test_wrong_fixes_that_agree_are_refused_while_the_autopilots_gnss_has_a_fix(off_m: float) -> None:
    flight = Flight()
    flight.fly(60.0)  # a minute without a match: unseeded, the filter would be lost by now
    assert flight.nav.state().sigma_m <= GNSS_SEED_FLOOR_M + 1e-6
    accepted = []
    for _ in range(8):
        flight.fly(0.5)
        accepted.append(flight.fuse(*wrong_place(flight.boot_s, off_m)))
    assert not any(accepted)
    assert flight.off_m() < 1.0
    assert flight.nav.state().since_fix_s is None  # nothing fused: nothing would be sent


def test_without_a_gnss_fix_the_search_stays_wide_and_the_first_right_fixes_start_navigation() -> None:
    for fix_type in (None, 1):  # no GPS_RAW_INT at all, or a receiver without a fix
        flight = Flight()
        flight.fly(30.0, fix_type)
        assert flight.nav.state().sigma_m > 100.0
    seeded = Flight()
    seeded.fly(30.0)
    for _ in range(3):
        seeded.fly(0.5)
        seeded.fuse(*where(seeded.boot_s))
    assert seeded.nav.state().since_fix_s is not None and seeded.off_m() < 5.0


def test_from_the_first_fused_fix_on_the_receiver_is_not_listened_to() -> None:
    """After lock a GNSS that jumps (spoofed, or orthonav's own GPS_INPUT as the first
    receiver) must not pull the navigation: only visual fixes and dead reckoning move it."""
    flight = Flight()
    flight.fly(10.0)
    flight.fly(0.5)
    assert flight.fuse(*where(flight.boot_s))
    sigma_after_fix = flight.nav.state().sigma_m
    flight.fly(5.0)
    assert flight.nav.state().sigma_m > sigma_after_fix  # dead reckoning grows it: not re-seeded


def test_the_seed_can_be_turned_off_for_a_start_under_spoofing() -> None:
    flight = Flight(gnss_seed=False)
    flight.fly(30.0)
    assert flight.nav.state().sigma_m > 100.0


def test_the_autopilots_receiver_is_reported_with_its_place_and_accuracy_while_fresh() -> None:
    """GPS_RAW_INT's h_acc (mm) is what tells orthonav's own GPS_INPUT from a GNSS at the same
    place (Companion._echoes_ours); a receiver heard from no more is none."""
    flight = Flight()
    flight.fly(3.0)
    now = flight.boot_s + BOOT_TO_UNIX_S
    [receiver] = flight.telemetry.receivers(now)
    assert receiver.index == 0 and receiver.accuracy_m == pytest.approx(0.3)
    assert distance_m(receiver.lat, receiver.lon, *where(flight.boot_s)) < SPEED_MPS * 1.0 + 0.5
    flight.fly(3.0, fix_type=None)
    assert flight.telemetry.receivers(flight.boot_s + BOOT_TO_UNIX_S) == []
