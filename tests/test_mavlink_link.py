"""MAVLink link, telemetry and message builders: loopback UDP, bad input, clocks, wire formats."""

from __future__ import annotations

import math
import socket
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers_timing import slowdown

pytest.importorskip("pymavlink")

from orthonav.errors import OrthonavError
from orthonav.fusion import NavState
from orthonav.geo import destination
from orthonav.mavlink import messages
from orthonav.mavlink.link import MavLink, dialect, statustext_chunks
from orthonav.mavlink.peer import PEER_MIN_MESSAGES, PEER_PROBATION_S
from orthonav.mavlink.telemetry import Telemetry

LAT, LON = 47.02, -99.15


def wait_for(link: MavLink, done: Callable[[list[Any]], bool], timeout_s: float = 2.0) -> list[Any]:
    """Poll ``link`` until ``done(messages so far)``; the messages."""
    got: list[Any] = []
    deadline = time.monotonic() + timeout_s
    while not done(got) and time.monotonic() < deadline:
        got += link.poll()
        time.sleep(0.005)
    return got


def types(msgs: list[Any]) -> list[str]:
    return [m.get_type() for m in msgs]


def wire(msg: Any, system: int = 1, component: int = 1) -> Any:
    """``msg`` as it arrives: packed by a sender with these ids and decoded by pymavlink."""
    packed = msg.pack(dialect().MAVLink(None, system, component))
    decoded = dialect().MAVLink(None).parse_buffer(packed)
    assert decoded is not None and len(decoded) == 1
    return decoded[0]


@pytest.fixture
def pair() -> Iterator[tuple[MavLink, MavLink]]:
    """(listener on a free port, vehicle sending to it): the transport of the usual deployment.
    The listener answers whoever sends, as a vehicle does; whom a companion believes is tested
    in test_companion_faults."""
    companion = MavLink("udpin:127.0.0.1:0", role="vehicle").open()
    with companion, MavLink(f"udpout:127.0.0.1:{companion.local_port}", role="vehicle") as vehicle:
        yield companion, vehicle


# --- link ---------------------------------------------------------------------------------


def test_udpout_vehicle_and_udpin_companion_talk_both_ways() -> None:
    companion = MavLink("udpin:127.0.0.1:0").open()
    with companion, MavLink(f"udpout:127.0.0.1:{companion.local_port}", role="vehicle") as vehicle:
        _talk_both_ways(companion, vehicle)


def _talk_both_ways(companion: MavLink, vehicle: MavLink) -> None:
    # The companion believes an autopilot once its stream has run unbroken for a while.
    started, got = time.monotonic(), []
    while "HEARTBEAT" not in types(got) and time.monotonic() - started < 5.0 * slowdown():
        vehicle.heartbeat()
        got += wait_for(companion, lambda m: bool(m), timeout_s=0.1)
    assert time.monotonic() - started >= PEER_PROBATION_S
    beat = got[types(got).index("HEARTBEAT")]
    mavlink = dialect()
    assert (beat.type, beat.autopilot) == (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert (beat.get_srcSystem(), beat.get_srcComponent()) == (1, 1)
    # The listening side learnt the vehicle's address from that packet and can answer.
    companion.heartbeat()
    back = wait_for(vehicle, lambda m: "HEARTBEAT" in types(m))
    beat = back[types(back).index("HEARTBEAT")]
    assert (beat.type, beat.autopilot) == (mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID)
    assert beat.get_srcComponent() == mavlink.MAV_COMP_ID_ONBOARD_COMPUTER
    assert companion.stats.received >= 1 and companion.stats.sent == 1 and vehicle.stats.received >= 1
    assert companion.stats.unconfirmed >= PEER_MIN_MESSAGES - 1


def test_reverse_pairing_vehicle_listens_companion_sends_first() -> None:
    with (
        MavLink("udp:127.0.0.1:0", role="vehicle") as vehicle,
        MavLink(f"udpout:127.0.0.1:{vehicle.local_port}") as companion,
    ):
        vehicle.heartbeat()  # no peer known yet: goes nowhere, and does not fail
        companion.heartbeat()
        assert "HEARTBEAT" in types(wait_for(vehicle, lambda m: "HEARTBEAT" in types(m)))
        vehicle.heartbeat()
        assert "HEARTBEAT" in types(wait_for(companion, lambda m: "HEARTBEAT" in types(m)))


def test_garbage_truncated_and_corrupt_packets_are_counted_and_skipped(pair: tuple[MavLink, MavLink]) -> None:
    companion, _ = pair
    good = dialect().MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3).pack(dialect().MAVLink(None, 7, 1))
    corrupt = bytearray(good)
    corrupt[-1] ^= 0xFF
    datagrams = [
        bytes(range(256)) * 2,  # noise, with stray start-of-frame bytes in it
        good[:7],  # truncated: its missing tail must not be taken from the next datagram
        good,
        bytes(corrupt),  # bad CRC
        b"\xfd\x09",  # a header cut short
        good,
    ]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        for data in datagrams:
            sock.sendto(data, ("127.0.0.1", companion.local_port))
    got = wait_for(companion, lambda m: len(m) >= 2, timeout_s=1.0)
    time.sleep(0.05)
    got += companion.poll()
    assert types(got) == ["HEARTBEAT", "HEARTBEAT"]
    assert all(m.get_srcSystem() == 7 for m in got)
    assert companion.stats.bad >= 4  # noise (one or more pieces), truncated, CRC, short header
    assert companion.stats.received == 2


def test_poll_returns_at_most_max_messages_and_keeps_the_rest(pair: tuple[MavLink, MavLink]) -> None:
    companion, vehicle = pair
    for _ in range(5):
        vehicle.heartbeat()
    time.sleep(0.05)
    first = companion.poll(max_messages=2)
    rest = wait_for(companion, lambda m: len(m) >= 3, timeout_s=1.0)
    assert len(first) == 2 and len(rest) == 3


def test_statustext_is_split_between_words_into_chunks_of_50(pair: tuple[MavLink, MavLink]) -> None:
    companion, vehicle = pair
    text = "visual fixes lost for 12 s: no position sent to the autopilot until they return (sigma 80 m)"
    vehicle.statustext(4, text)
    vehicle.statustext(6, "short")
    got = wait_for(companion, lambda m: len(m) >= 3)
    long_chunks, short = got[:-1], got[-1]
    assert len(long_chunks) == 2
    assert all(len(m.text) <= 50 and m.severity == 4 for m in long_chunks)
    assert [m.chunk_seq for m in long_chunks] == [0, 1] and long_chunks[0].id == long_chunks[1].id != 0
    assert " ".join(m.text for m in long_chunks) == text
    assert (short.text, short.id, short.severity) == ("short", 0, 6)


def test_statustext_of_any_length_stays_within_four_ascii_chunks() -> None:
    chunks = statustext_chunks("é" + "x" * 500)
    assert len(chunks) == 4 and chunks[-1].endswith("...")
    assert all(len(c) <= 50 and c.isascii() for c in chunks)
    assert statustext_chunks("") == ["-"]


def test_silence_is_timed_from_open_then_from_the_last_message() -> None:
    now = [100.0]
    with MavLink("udpin:127.0.0.1:0", role="vehicle", clock=lambda: now[0]) as companion:
        assert companion.silent_for() == 0.0
        now[0] = 103.5
        assert companion.silent_for() == 3.5
        with MavLink(f"udpout:127.0.0.1:{companion.local_port}", role="vehicle") as vehicle:
            vehicle.heartbeat()
            wait_for(companion, lambda m: len(m) >= 1)
        assert companion.stats.last_receive_s == 103.5
        assert companion.silent_for(110.0) == 6.5


def test_reconnect_listens_on_the_port_first_bound_and_keeps_receiving() -> None:
    companion = MavLink("udpin:127.0.0.1:0", role="vehicle").open()
    port = companion.local_port
    assert companion.url == f"udpin:127.0.0.1:{port}"
    with companion, MavLink(f"udpout:127.0.0.1:{port}", role="vehicle") as vehicle:
        vehicle.heartbeat()
        assert wait_for(companion, lambda m: len(m) >= 1)
        companion.reconnect()
        assert companion.stats.reconnects == 1 and companion.local_port == port
        vehicle.heartbeat()
        assert types(wait_for(companion, lambda m: len(m) >= 1)) == ["HEARTBEAT"]


def test_a_tcp_peer_that_hangs_up_is_noticed_and_reconnect_dials_again() -> None:
    server = socket.create_server(("127.0.0.1", 0))
    heartbeat = dialect().MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(dialect().MAVLink(None, 1, 1))
    with server, MavLink(f"tcp:127.0.0.1:{server.getsockname()[1]}") as companion:
        peer, _ = server.accept()
        with peer:
            peer.sendall(heartbeat)
            assert types(wait_for(companion, lambda m: len(m) >= 1)) == ["HEARTBEAT"]
        deadline = time.monotonic() + 2.0
        while companion.stats.errors == 0 and time.monotonic() < deadline:
            assert companion.poll() == []  # the hang-up raises nothing
            time.sleep(0.005)
        assert companion.stats.errors == 1 and companion.poll() == []
        companion.heartbeat()  # not sent: the peer is gone
        assert companion.stats.errors == 2 and companion.stats.sent == 0
        companion.reconnect()
        peer, _ = server.accept()
        with peer:
            companion.heartbeat()
            assert companion.stats.sent == 1 and peer.recv(100)[0] == 0xFD  # a MAVLink 2 frame


@pytest.mark.parametrize("url", ["localhost:14550", "udp://127.0.0.1:14550", "udpin:14550", "foo"])
def test_unknown_url_forms_are_rejected_with_the_accepted_ones(url: str) -> None:
    with pytest.raises(OrthonavError, match="udpin:HOST:PORT"):
        MavLink(url)


def test_an_unusable_address_is_a_clear_error_and_polling_closed_link_too() -> None:
    with pytest.raises(OrthonavError, match="cannot open"):
        MavLink("udpin:203.0.113.1:14550").open()  # not an address of this machine
    with pytest.raises(OrthonavError, match="not open"):
        MavLink("udpin:127.0.0.1:0").poll()


# --- message builders ------------------------------------------------------------------------


def nav_state(status: str = "fixed", lat: float = LAT, lon: float = LON, **changes: Any) -> NavState:
    values: dict[str, Any] = {
        "time_s": 1_767_225_600.0,
        "lat": lat,
        "lon": lon,
        "heading_deg": 90.0,
        "vel_east_mps": 15.0,
        "vel_north_mps": 0.0,
        "covariance_enu_m2": np.array([[25.0, 3.0], [3.0, 100.0]]),
        "heading_sigma_deg": 2.0,
        "status": status,
        "since_fix_s": 0.5,
        "alt_agl_m": 300.0,
    }
    return NavState(**{**values, **changes})


def test_gps_time_of_new_year_2026_counts_from_the_gps_epoch_with_18_leap_seconds() -> None:
    unix_s = datetime(2026, 1, 1, tzinfo=UTC).timestamp()
    gps_s = (datetime(2026, 1, 1, tzinfo=UTC) - datetime(1980, 1, 6, tzinfo=UTC)).total_seconds() + 18
    assert messages.gps_time(unix_s) == (int(gps_s // 604800), int(gps_s % 604800) * 1000)
    assert messages.gps_time(unix_s) == (2399, (4 * 86400 + 18) * 1000)  # a Thursday
    assert messages.gps_time(unix_s + 0.1234) == (2399, (4 * 86400 + 18) * 1000 + 123)


def test_gps_input_on_the_wire_has_a_3d_fix_accuracies_and_gps_time() -> None:
    capture_s = datetime(2026, 1, 1, tzinfo=UTC).timestamp() + 0.25
    msg = wire(messages.gps_input(nav_state(), capture_s, alt_msl_m=812.5))
    mavlink = dialect()
    worst_sigma = math.sqrt(max(np.linalg.eigvalsh([[25.0, 3.0], [3.0, 100.0]])))
    assert msg.get_type() == "GPS_INPUT"
    assert (msg.lat, msg.lon) == (round(LAT * 1e7), round(LON * 1e7))
    assert (msg.fix_type, msg.satellites_visible) == (3, 10)
    assert msg.time_usec == round(capture_s * 1e6)
    assert (msg.time_week, msg.time_week_ms) == (2399, (4 * 86400 + 18) * 1000 + 250)
    assert msg.horiz_accuracy == pytest.approx(worst_sigma, rel=1e-6)
    assert msg.hdop == pytest.approx(worst_sigma / messages.UERE_M, rel=1e-6)
    assert msg.alt == pytest.approx(812.5) and msg.vert_accuracy > 0
    assert (msg.vn, msg.ve, msg.yaw) == (pytest.approx(0.0), pytest.approx(15.0), 0)
    assert msg.ignore_flags == mavlink.GPS_INPUT_IGNORE_FLAG_VEL_VERT
    # The velocity is claimed no better than two positions a second apart can tell it.
    assert msg.speed_accuracy == pytest.approx(math.sqrt(2.0) * worst_sigma, rel=1e-6)
    sharp = np.array([[0.04, 0.0], [0.0, 0.04]])
    assert (
        wire(messages.gps_input(nav_state(covariance_enu_m2=sharp), capture_s, 812.5)).speed_accuracy == 1.0
    )
    # Dead reckoning, the velocity is the autopilot's own: claimed as none.
    reckoned = nav_state("dead reckoning", since_fix_s=3.0)
    assert (
        wire(messages.gps_input(reckoned, capture_s, 812.5)).speed_accuracy
        == messages.UNKNOWN_SPEED_SIGMA_MPS
    )


def test_past_the_reckoning_limit_only_a_measured_velocity_carries_the_position_out() -> None:
    """Beyond ``max_reckoning_s`` without a fix the position goes out only while a ground velocity
    measured from the frames is fresh (orthonav's own odometry, not the autopilot's velocity
    handed back); never before a first fix, never past ``max_sigma_m``."""
    velocity_cov = np.eye(2) * 0.16
    measured = {"velocity_covariance_enu_m2ps2": velocity_cov, "since_velocity_s": 0.4}
    fresh = nav_state("dead reckoning", since_fix_s=20.0, **measured)
    assert messages.withheld_because(fresh, 50.0, 3.0) == ""
    stale = replace(fresh, since_velocity_s=messages.MEASURED_VELOCITY_S + 0.5)
    never = nav_state("dead reckoning", since_fix_s=20.0)
    for state in (stale, never):
        assert "no visual fix for 20 s" in messages.withheld_because(state, 50.0, 3.0)
    assert "no visual fix yet" in messages.withheld_because(replace(fresh, since_fix_s=None), 50.0, 3.0)
    assert "uncertainty 10 m > 8 m" in messages.withheld_because(fresh, 8.0, 3.0)
    # Within the limit the velocity's source does not matter.
    assert messages.withheld_because(replace(never, since_fix_s=2.0), 50.0, 3.0) == ""
    assert messages.speed_sigma_mps(fresh) == pytest.approx(0.4)
    assert messages.speed_sigma_mps(stale) == messages.UNKNOWN_SPEED_SIGMA_MPS


def test_gps_input_without_altitude_flags_it_ignored_and_yaw_uses_36000_for_north() -> None:
    mavlink = dialect()
    msg = wire(messages.gps_input(nav_state(heading_deg=0.0), 1.7e9, alt_msl_m=None, send_yaw=True))
    for flag in ("ALT", "VDOP", "VERTICAL_ACCURACY", "VEL_VERT"):
        assert msg.ignore_flags & getattr(mavlink, f"GPS_INPUT_IGNORE_FLAG_{flag}")
    assert not msg.ignore_flags & mavlink.GPS_INPUT_IGNORE_FLAG_HORIZONTAL_ACCURACY
    assert msg.yaw == 36000
    assert wire(messages.gps_input(nav_state(heading_deg=90.0), 1.7e9, None, send_yaw=True)).yaw == 9000


@pytest.mark.parametrize(
    "state",
    [
        nav_state("lost"),
        nav_state("uninitialised"),
        nav_state(covariance_enu_m2=np.full((2, 2), np.nan)),
    ],
)
def test_an_untrusted_state_cannot_become_a_position_message(state: NavState) -> None:
    origin = (LAT, LON)
    with pytest.raises(OrthonavError, match="refusing"):
        messages.gps_input(state, 1.7e9, 500.0)
    with pytest.raises(OrthonavError, match="refusing"):
        messages.global_position_sensor(state, 1.7e9, 500.0)
    with pytest.raises(OrthonavError, match="refusing"):
        messages.vision_position_estimate(state, origin, 1.7e9)
    with pytest.raises(OrthonavError, match="refusing"):
        messages.odometry(state, origin, 1.7e9)


def test_vision_position_estimate_is_ned_from_the_origin_with_the_covariance_layout() -> None:
    lat, lon = destination(*destination(LAT, LON, 0.0, 100.0), 90.0, 50.0)
    state = nav_state(lat=lat, lon=lon, heading_deg=270.0)
    extras = messages.PoseExtras(pitch_deg=2.0, vert_sigma_m=4.0)
    msg = wire(messages.vision_position_estimate(state, (LAT, LON), 1.7e9, extras))
    assert (msg.x, msg.y, msg.z) == (pytest.approx(100.0, abs=0.01), pytest.approx(50.0, abs=0.01), -300.0)
    assert msg.yaw == pytest.approx(-math.pi / 2) and msg.pitch == pytest.approx(math.radians(2.0))
    assert msg.usec == 1_700_000_000_000_000
    cov = msg.covariance
    assert len(cov) == 21
    # Row-major upper triangle: [0] xx (north), [1] xy, [6] yy (east), [11] zz, [20] yaw-yaw.
    assert (cov[0], cov[1], cov[6], cov[11]) == (100.0, 3.0, 25.0, 16.0)
    assert cov[20] == pytest.approx(math.radians(2.0) ** 2)
    assert cov[2] == cov[5] == cov[19] == 0.0


def test_odometry_frames_quaternion_and_body_velocity() -> None:
    mavlink = dialect()
    state = nav_state(lat=destination(LAT, LON, 90.0, 20.0)[0], lon=destination(LAT, LON, 90.0, 20.0)[1])
    msg = wire(messages.odometry(state, (LAT, LON), 1.7e9))
    assert (msg.frame_id, msg.child_frame_id) == (mavlink.MAV_FRAME_LOCAL_FRD, mavlink.MAV_FRAME_BODY_FRD)
    assert (msg.x, msg.y) == (pytest.approx(0.0, abs=0.01), pytest.approx(20.0, abs=0.01))
    half = math.sqrt(0.5)
    assert msg.q == pytest.approx([half, 0.0, 0.0, half])  # heading east: 90 deg about down
    assert (msg.vx, msg.vy) == (pytest.approx(15.0), pytest.approx(0.0, abs=1e-5))  # all forward
    assert math.isnan(msg.velocity_covariance[0]) and math.isnan(msg.yawspeed)
    assert msg.pose_covariance[0] == 100.0 and msg.estimator_type == mavlink.MAV_ESTIMATOR_TYPE_VISION


def mavlink_definition(name: str) -> Any:
    """The message as MAVLink's XML defines it (pymavlink's copy of common.xml), parsed by pymavlink."""
    from pymavlink.dialects import v20
    from pymavlink.generator import mavparse

    xml = mavparse.MAVXML(str(Path(v20.__file__).parent / "common.xml"), mavparse.PROTOCOL_2_0)
    return next(m for m in xml.message if m.name == name)


def test_global_position_sensor_round_trips_field_by_field_as_mavlink_defines_it() -> None:
    mavlink = dialect()
    lat, lon = 47.123456789, -99.12345675  # 7th decimals that must round, not truncate
    state = nav_state(lat=lat, lon=lon)
    built = messages.global_position_sensor(
        state, 1_767_225_600.25, 812.5, sent_unix_s=1_767_225_600.40, vert_sigma_m=6.0, target=(3, 1)
    )
    definition = mavlink_definition("GLOBAL_POSITION_SENSOR")
    # The wire format is the definition's: id, fields and CRC seed (which hashes names and types).
    assert (built.get_msgId(), built.crc_extra) == (definition.id, definition.crc_extra) == (296, 158)
    assert built.fieldnames == [f.name for f in definition.fields]
    msg = wire(built, system=1, component=197)
    assert (msg.target_system, msg.target_component, msg.id) == (3, 1, messages.SENSOR_ID)
    assert (msg.source, msg.flags) == (mavlink.GLOBAL_POSITION_SRC_VISION, 0)  # healthy, not primary
    assert (msg.lat, msg.lon) == (471234568, -991234568)
    assert abs(msg.lat * 1e-7 - lat) <= 0.5e-7 and abs(msg.lon * 1e-7 - lon) <= 0.5e-7
    assert msg.time_usec == 1_767_225_600_400_000  # sent
    assert msg.processing_time == 150_000  # true 150 ms before it was sent
    assert msg.eph == pytest.approx(state.sigma_m, rel=1e-6) and state.sigma_m > 5.0  # the worst axis
    assert (msg.alt, msg.epv) == (812.5, 6.0)
    assert math.isnan(msg.alt_ellipsoid)


def test_global_position_sensor_marks_what_it_does_not_know_invalid() -> None:
    definition = {f.name: f.invalid for f in mavlink_definition("GLOBAL_POSITION_SENSOR").fields}
    msg = wire(messages.global_position_sensor(nav_state(), 1.7e9 + 0.5, None, sent_unix_s=1.7e9))
    for name in ("alt", "epv", "alt_ellipsoid"):
        assert definition[name] == "NaN" and math.isnan(getattr(msg, name)), name
    assert math.isfinite(msg.eph) and msg.processing_time == 0  # never negative
    assert (msg.target_system, msg.target_component) == (0, 0)  # broadcast unless told


def test_upper_triangle_marks_an_unknown_covariance_with_nan_first() -> None:
    full = np.arange(36, dtype=float).reshape(6, 6)
    tri = messages.upper_triangle(full)
    assert tri[:6] == [0, 1, 2, 3, 4, 5] and tri[6:11] == [7, 8, 9, 10, 11] and tri[-1] == 35
    full[3, 3] = np.nan
    unknown = messages.upper_triangle(full)
    assert math.isnan(unknown[0]) and len(unknown) == 21


# --- telemetry -------------------------------------------------------------------------------

BOOT_UNIX_S = 1_767_225_600.0


def telemetry_at(
    boot_s: float, lat: float = LAT, lon: float = LON, system: int = 1, component: int = 1
) -> list[Any]:
    """GLOBAL_POSITION_INT and ATTITUDE (heading 30 deg) stamped ``boot_s`` after the autopilot booted."""
    mavlink, ms = dialect(), round(boot_s * 1000)
    return [
        wire(
            mavlink.MAVLink_global_position_int_message(
                ms, round(lat * 1e7), round(lon * 1e7), 600_000, 300_000, 150, -220, 0, 3000
            ),
            system,
            component,
        ),
        wire(
            mavlink.MAVLink_attitude_message(ms, 0.01, -0.02, math.radians(30.0), 0, 0, 0), system, component
        ),
    ]


def system_time(boot_s: float, unix_s: float) -> Any:
    return wire(dialect().MAVLink_system_time_message(round(unix_s * 1e6), round(boot_s * 1000)))


def feed(telemetry: Telemetry, msgs: list[Any], now_s: float) -> list[Any]:
    return [event for msg in msgs for event in telemetry.ingest(msg, now_s)]


def test_ins_sample_from_fresh_telemetry_on_the_unix_clock() -> None:
    tel = Telemetry(max_age_s=1.0)
    arrival = BOOT_UNIX_S + 10.02
    assert feed(tel, [system_time(10.0, BOOT_UNIX_S + 10.0), *telemetry_at(10.0)], arrival) == []
    sample = tel.ins_sample(arrival + 0.1)
    assert sample is not None and tel.problem is None
    assert sample.time_s == pytest.approx(BOOT_UNIX_S + 10.0)  # via SYSTEM_TIME, not the arrival
    assert (sample.lat, sample.lon) == (pytest.approx(LAT), pytest.approx(LON))
    assert (sample.vel_north_mps, sample.vel_east_mps) == (pytest.approx(1.5), pytest.approx(-2.2))
    assert sample.heading_deg == pytest.approx(30.0) and sample.alt_agl_m == pytest.approx(300.0)
    assert tel.attitude() == pytest.approx((30.0, math.degrees(-0.02), math.degrees(0.01)))
    assert tel.alt_msl_m() == pytest.approx(600.0) and tel.clock.source == "SYSTEM_TIME"


def test_local_position_ned_velocity_is_preferred_when_fresh() -> None:
    tel = Telemetry()
    local = wire(dialect().MAVLink_local_position_ned_message(10_000, 5.0, 6.0, -300.0, 1.25, -2.5, 0.0))
    feed(tel, [*telemetry_at(10.0), local], 100.0)
    sample = tel.ins_sample(100.0)
    assert sample is not None
    assert (sample.vel_north_mps, sample.vel_east_mps) == (1.25, -2.5)
    # Without SYSTEM_TIME the boot clock maps through the arrival time.
    assert sample.time_s == pytest.approx(100.0) and tel.clock.source == "arrival time"


def test_missing_or_stale_telemetry_gives_no_sample_and_says_why() -> None:
    tel = Telemetry(max_age_s=1.0)
    assert tel.ins_sample(0.0) is None and "GLOBAL_POSITION_INT" in tel.problem
    position, attitude = telemetry_at(10.0)
    feed(tel, [position], 50.0)
    assert tel.ins_sample(50.1) is None and tel.problem == "no ATTITUDE received"
    feed(tel, [attitude], 50.0)
    assert tel.ins_sample(50.5) is not None
    assert tel.ins_sample(53.0) is None and "3.0 s old (max 1 s)" in tel.problem
    assert tel.attitude(53.0) is None and tel.attitude() is not None


def test_a_position_of_zero_zero_is_no_position() -> None:
    tel = Telemetry()
    feed(tel, telemetry_at(10.0, lat=0.0, lon=0.0), 5.0)
    assert tel.ins_sample(5.0) is None and "at 0 N 0 E" in tel.problem


def test_reboot_is_reported_and_forgets_the_old_boot() -> None:
    tel = Telemetry()
    feed(tel, [system_time(500.0, BOOT_UNIX_S + 500.0), *telemetry_at(500.0)], BOOT_UNIX_S + 500.0)
    events = feed(tel, [telemetry_at(1.0)[1]], BOOT_UNIX_S + 501.0)  # ATTITUDE of a new boot
    assert [e.kind for e in events] == ["reboot"] and "500.0 s to 1.0 s" in str(events[0])
    assert tel.pop_events() == events and tel.pop_events() == []
    assert tel.ins_sample(BOOT_UNIX_S + 501.0) is None and "no GLOBAL_POSITION_INT" in tel.problem
    feed(tel, telemetry_at(1.1), BOOT_UNIX_S + 501.1)
    sample = tel.ins_sample(BOOT_UNIX_S + 501.1)
    assert sample is not None and sample.time_s == pytest.approx(BOOT_UNIX_S + 501.1)  # new mapping


def test_unix_time_jump_and_clock_mismatch_are_reported() -> None:
    tel = Telemetry()
    arrival = BOOT_UNIX_S + 20.0
    feed(tel, [system_time(20.0, arrival), *telemetry_at(20.0)], arrival)
    events = feed(tel, [system_time(21.0, arrival + 3601.0)], arrival + 1.0)
    assert [e.kind for e in events] == ["unix time jump", "clock mismatch"]
    assert "+3600.0 s" in str(events[0])
    # The autopilot's UNIX clock is off: samples stay on the companion's clock.
    feed(tel, telemetry_at(21.5), arrival + 1.5)
    sample = tel.ins_sample(arrival + 1.5)
    assert tel.clock.source == "arrival time" and sample.time_s == pytest.approx(arrival + 1.5)


def test_boot_time_leaping_ahead_of_arrivals_is_reported() -> None:
    tel = Telemetry()
    feed(tel, telemetry_at(10.0), 100.0)
    events = feed(tel, telemetry_at(70.0), 101.0)
    assert [e.kind for e in events] == ["boot time jump"] and "59.0 s ahead" in str(events[0])


def test_telemetry_from_other_components_and_systems_is_ignored() -> None:
    mavlink = dialect()
    tel = Telemetry()
    feed(tel, [wire(mavlink.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3), system=1)], 10.0)
    assert tel.system_id == 1  # locked onto the first autopilot heartbeat
    feed(tel, telemetry_at(10.0, component=154) + telemetry_at(10.0, system=2), 10.0)
    assert tel.ins_sample(10.0) is None
    feed(tel, telemetry_at(10.0), 10.0)
    assert tel.ins_sample(10.0) is not None


def attitude_msg(boot_s: float, yaw_deg: float, pitch_deg: float, roll_deg: float) -> Any:
    rad = math.radians
    return wire(
        dialect().MAVLink_attitude_message(
            round(boot_s * 1000), rad(roll_deg), rad(pitch_deg), rad(yaw_deg), 0.0, 0.0, 0.0
        )
    )


def test_attitude_at_a_frames_capture_time_is_interpolated_with_an_honest_sigma() -> None:
    """A copter pitching 20 deg/s: a frame captured between two ATTITUDEs gets the attitude of its
    time (not the newest), its sigma grows with the rate, heading interpolates across north."""
    tel = Telemetry()
    for i in range(11):  # 10 Hz, pitch -0 -> -20 deg over 1 s, heading 350 -> 10 deg
        boot_s = 10.0 + 0.1 * i
        feed(tel, [attitude_msg(boot_s, (350.0 + 2.0 * i) % 360.0, -2.0 * i, 0.0)], 100.0 + 0.1 * i)
    attitude, sigma_deg = tel.attitude_at(100.55)
    assert attitude.pitch_deg == pytest.approx(-11.0, abs=1e-6)
    assert attitude.heading_deg == pytest.approx(1.0, abs=1e-6)
    assert tel.attitude().pitch_deg == pytest.approx(-20.0)  # what the newest would have said
    assert 2.0 <= sigma_deg <= 4.0  # 20 deg/s times (0.1 s spacing + 0.02 s capture time)
    steady = Telemetry()
    for i in range(11):
        feed(steady, [attitude_msg(10.0 + 0.1 * i, 90.0, -5.0, 2.0)], 100.0 + 0.1 * i)
    assert steady.attitude_at(100.55)[1] == pytest.approx(0.3)
    # Beyond reach (older than the history, or long after the newest): no attitude of that time.
    assert tel.attitude_at(99.0) is None and tel.attitude_at(101.0 + 0.6) is None


def test_an_autopilot_unix_clock_a_second_off_ours_is_not_used_for_frames() -> None:
    """ArduPilot SITL's GPS time runs 0.4-0.8 s behind the wall clock: telemetry stays on our
    clock (arrival times), where a frame's capture time is, and the mismatch is reported."""
    tel = Telemetry()
    arrival = BOOT_UNIX_S + 20.0
    feed(tel, telemetry_at(20.0), arrival)
    events = feed(tel, [system_time(20.0, arrival - 0.8)], arrival)
    assert [e.kind for e in events] == ["clock mismatch"] and "-0.80 s" in str(events[0])
    sample = tel.ins_sample(arrival)
    assert tel.clock.source == "arrival time" and sample.time_s == pytest.approx(arrival)
    close = Telemetry()
    feed(close, [system_time(20.0, arrival - 0.05), *telemetry_at(20.0)], arrival)
    assert close.clock.source == "SYSTEM_TIME"
