"""The SITL fault flights' harness without SITL: the link relay and the stalled camera act only
inside the fault window (counted from GNSS loss), the bank flight's loiter is steeper than 60 deg,
and a flight's verdict follows from what the companion logged."""

from __future__ import annotations

import json
import math
import socket
import time
from contextlib import ExitStack
from pathlib import Path
from types import SimpleNamespace

from orthonav.bench.sitl import SCENARIOS, SitlConfig, Track, vehicle_params
from orthonav.bench.sitl_faults import FAULTS, Injector, fault_config, grade_fault

GRAVITY = 9.80665


def _udp(timeout_s: float = 0.3) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(timeout_s)
    return sock


def _passes(sender: socket.socket, receiver: socket.socket, to: tuple[str, int], tries: int = 3) -> bool:
    """Whether a datagram ``sender`` sends to ``to`` reaches ``receiver``."""
    for _ in range(tries):
        sender.sendto(b"ping", to)
        try:
            receiver.recvfrom(100)
            return True
        except TimeoutError:
            continue
    return False


def _injector(name: str) -> tuple[Injector, dict, SimpleNamespace]:
    fault = FAULTS[name]
    injector = Injector(fault, fault_config(fault, SitlConfig()))
    return injector, {}, SimpleNamespace(track=Track())


def _open_window(injector: Injector, flight: dict, gcs: SimpleNamespace, into_s: float) -> None:
    """GNSS went ``at_s + into_s`` ago: ``into_s`` seconds into the fault (negative: before it)."""
    flight["gnss_off_at"] = time.time() - injector.fault.at_s - into_s
    injector.in_flight(gcs, flight)  # type: ignore[arg-type]


def test_the_link_is_cut_both_ways_inside_the_window_only(tmp_path: Path) -> None:
    injector, flight, gcs = _injector("copter-link-loss")
    with _udp() as companion, _udp() as autopilot, ExitStack() as stack:
        port, camera = injector.links(stack, companion.getsockname()[1], tmp_path / "camera")
        assert camera == tmp_path / "camera"
        relay = ("127.0.0.1", port)
        assert _passes(autopilot, companion, relay)  # before GNSS loss: a plain relay
        autopilot.sendto(b"hello", relay)
        _, companion_side = companion.recvfrom(100)
        assert _passes(companion, autopilot, companion_side)
        _open_window(injector, flight, gcs, 1.0)
        assert flight["fault_to"] - flight["fault_from"] == injector.fault.duration_s
        assert not _passes(autopilot, companion, relay) and not _passes(companion, autopilot, companion_side)
        injector.clock.started = time.time() - injector.fault.at_s - injector.fault.duration_s - 0.5
        assert _passes(autopilot, companion, relay) and _passes(companion, autopilot, companion_side)


def test_a_stalled_camera_delivers_nothing_inside_the_window(tmp_path: Path) -> None:
    injector, flight, gcs = _injector("copter-camera-stall")
    folder = tmp_path / "camera"
    with ExitStack() as stack:
        port, raw = injector.links(stack, 14550, folder)
        assert port == 14550 and raw != folder

        def delivered(name: str) -> bool:
            (raw / name).write_bytes(b"frame")
            deadline = time.monotonic() + 2.0
            while (raw / name).exists() and time.monotonic() < deadline:
                time.sleep(0.02)
            return (folder / name).exists()

        assert delivered("a.jpg")
        _open_window(injector, flight, gcs, 1.0)
        assert not delivered("b.jpg") and not delivered("c.jpg")
        injector.clock.started = time.time() - injector.fault.at_s - injector.fault.duration_s - 0.5
        assert delivered("d.jpg")
    assert injector.frame_relay is not None and injector.frame_relay.lost == 2


def test_the_bank_flight_loiters_steeper_than_60_deg_and_returns_gently() -> None:
    """A level turn of radius r at speed v banks atan(v^2 / (g r)): over 60 deg on the route's
    loiter, within the raised roll limit, and gentle on the loiter over home."""
    fault = FAULTS["plane-steep-bank"]
    params = vehicle_params(fault_config(fault, SitlConfig()), SCENARIOS[fault.scenario])
    bank = lambda radius: math.degrees(math.atan(params["AIRSPEED_CRUISE"] ** 2 / (GRAVITY * radius)))  # noqa: E731
    assert 60.0 < bank(params["WP_LOITER_RAD"]) < params["ROLL_LIMIT_DEG"]
    assert bank(params["RTL_RADIUS"]) < 30.0
    copter = vehicle_params(
        fault_config(FAULTS["copter-link-loss"], SitlConfig()), SCENARIOS[FAULTS["copter-link-loss"].scenario]
    )
    assert "ROLL_LIMIT_DEG" not in copter


def test_the_copter_faults_are_shorter_than_arducopter_bridges() -> None:
    """ArduCopter's EKF failsafe comes about 8 s after its last position: a longer silence lands
    the copter whatever the companion does, so the faults stay below it (a stalled camera still
    leaves the companion 3 s of dead reckoning) and above AP_GPS's 4 s timeout for the link."""
    assert 4.0 < FAULTS["copter-link-loss"].duration_s < 8.0
    assert FAULTS["copter-camera-stall"].duration_s < 8.0 + 3.0


def test_the_verdict_needs_no_wrong_message_a_fix_soon_after_and_a_completed_flight(tmp_path: Path) -> None:
    start = 1000.0
    flight = {
        "gnss_off_at": start - 25.0,
        "fault_from": start,
        "fault_to": start + 6.0,
        "ended_at": start + 90,
    }
    fused = [start - 1.0, start + 2.0, start + 7.5, start + 8.0]
    (tmp_path / "fly").mkdir()
    lines = [
        {"kind": "fix", "time_s": t, "capture_time_s": t - 0.3, "filter": {"accepted": True}} for t in fused
    ]
    lines.append({"kind": "event", "time_s": start + 7.0, "text": "no telemetry for 5 s"})
    (tmp_path / "fly" / "companion.jsonl").write_text("\n".join(json.dumps(r) for r in lines))
    estimate = [[start + s, 0.0, 0.0, 3.0 + s] for s in range(-5, 40)]
    (tmp_path / "track.json").write_text(json.dumps({"estimate": estimate}))
    good = {"completed": True, "orthonav_messages": {"sent": 400, "wrong": 0}}
    graded = grade_fault(tmp_path, flight, good, None)
    assert graded["resumed_s"] == 1.5 and graded["fixes_in_fault"] == 1 and graded["passed"]
    assert graded["fault_window_s"] == [25.0, 31.0] and graded["companion_events"] == ["no telemetry for 5 s"]
    assert graded["autopilot_error_after_max_m"] == 3.0 + 39
    for bad in ({**good, "completed": False}, {**good, "orthonav_messages": {"sent": 400, "wrong": 1}}):
        assert not grade_fault(tmp_path, flight, bad, None)["passed"]
    silent = grade_fault(
        tmp_path, {**flight, "fault_from": start + 9.0, "fault_to": start + 20.0}, good, None
    )
    assert silent["resumed_s"] is None and silent["fixes_in_fault"] == 0 and not silent["passed"]
