"""MAV_CMD_EXTERNAL_POSITION_ESTIMATE: built as MAVLink defines it, and sent by the companion only
where it helps ArduPilot (fixes resuming after a span without any), rate-limited."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from orthonav.errors import OrthonavError
from orthonav.mavlink import messages
from orthonav.mavlink.companion import Companion, CompanionConfig, CompanionStats
from orthonav.mavlink.link import dialect
from orthonav.types import Fix, Pose


def fix_at(lat: float = 47.123456789, lon: float = -99.12345675, sigma_m: float = 6.0) -> Fix:
    pose = Pose(lat, lon, 300.0, 90.0, 0.0, 0.0, lat, lon)
    return Fix(True, pose=pose, covariance_enu_m2=np.diag([sigma_m**2, (sigma_m / 2) ** 2]))


def wire(msg: object) -> object:
    """``msg`` packed by a companion (system 1, component 191) and decoded by pymavlink."""
    packed = msg.pack(dialect().MAVLink(None, 1, 191))
    decoded = dialect().MAVLink(None).parse_buffer(packed)
    assert decoded is not None and len(decoded) == 1
    return decoded[0]


def test_the_estimate_round_trips_as_mavlinks_command_defines_it() -> None:
    """COMMAND_INT in the global frame: latitude and longitude in 1e-7 degrees (rounded), param1
    the send time wrapped, param2 capture to send, param3 the fix's worst-axis 1-sigma, the
    altitude NaN as the definition asks."""
    mavlink = dialect()
    definition = mavlink.enums["MAV_CMD"][mavlink.MAV_CMD_EXTERNAL_POSITION_ESTIMATE]
    assert mavlink.MAV_CMD_EXTERNAL_POSITION_ESTIMATE == 43003
    assert "accuracy" in definition.param[3] and definition.param[5] == "Latitude"
    assert "NaN" in definition.param[7]
    sent_s = 1_767_225_712.40
    built = messages.external_position_estimate(fix_at(), sent_s - 0.25, sent_unix_s=sent_s, target=(1, 1))
    msg = wire(built)
    assert msg.get_type() == "COMMAND_INT" and msg.command == 43003
    assert (msg.target_system, msg.target_component, msg.frame) == (1, 1, mavlink.MAV_FRAME_GLOBAL)
    assert (msg.x, msg.y) == (471234568, -991234568)
    assert msg.param1 == pytest.approx(sent_s % messages.EXTERNAL_ESTIMATE_WRAP_S, abs=1e-4)
    assert 0.0 <= msg.param1 < 250.0
    assert msg.param2 == pytest.approx(0.25, abs=1e-6)
    assert msg.param3 == pytest.approx(6.0, rel=1e-6)  # the worse of 6 and 3 m
    assert math.isnan(msg.z)


def test_only_an_accepted_fix_becomes_an_estimate() -> None:
    with pytest.raises(OrthonavError, match="EXTERNAL_POSITION_ESTIMATE: an accepted fix expected"):
        messages.external_position_estimate(Fix(False, reason="no correlation"), 0.0)


def owner(output: str = "gps_input", system_id: int | None = 1, ardupilot: bool = True) -> SimpleNamespace:
    """The parts of a companion the reset uses: what it sends is collected."""
    sent: list = []
    return SimpleNamespace(
        config=CompanionConfig(output=output),
        telemetry=SimpleNamespace(system_id=system_id, component_id=1, ardupilot=ardupilot),
        link=SimpleNamespace(send=sent.append),
        stats=CompanionStats(),
        record=lambda *args: None,
        _last_fused_capture_s=None,
        _last_reset_s=-math.inf,
        sent=sent,
    )


def fly(companion: SimpleNamespace, captures: np.ndarray) -> list[float]:
    """Fused fixes at ``captures`` (each fused 0.2 s later): the capture times that reset."""
    resets = []
    for captured in captures:
        before = len(companion.sent)
        Companion._reset_after_gap(companion, fix_at(), float(captured), float(captured) + 0.2)
        if len(companion.sent) > before:
            resets.append(float(captured))
    return resets


def test_a_reset_follows_each_span_without_fixes_and_no_more_often_than_allowed() -> None:
    """Fixes twice a second with gaps: of 2 s (the autopilot was still sent positions), of 8 s
    (it dead-reckoned), and of 5 s again within 10 s of that: one reset, on the first fix after
    the long gap; none to an autopilot that is not ArduPilot (PX4 takes no such command), from
    an output ArduPilot does not fuse, or before the autopilot is known."""
    runs = (np.arange(0.0, 20.0, 0.5), np.arange(21.5, 26.5, 0.5), [34.0, 34.5, 35.0], [40.0, 40.5])
    captures = np.concatenate(runs)
    gaps = np.diff(captures)
    assert np.round(gaps[gaps > 0.5], 1).tolist() == [2.0, 8.0, 5.0]
    companion = owner()
    assert fly(companion, captures) == [34.0]
    assert companion.stats.position_resets == 1
    assert companion.sent[0].command == dialect().MAV_CMD_EXTERNAL_POSITION_ESTIMATE
    # Seen from 34 s on, the first fix has no gap before it; the 5 s gap, with no reset before, does.
    assert fly(owner(), captures[captures >= 34.0]) == [40.0]
    assert fly(owner(), np.array([0.0, 12.0, 30.0])) == [12.0, 30.0]  # long gaps, 18 s apart
    for output in ("vision", "odometry"):  # ArduPilot's ExternalNav takes it as well
        assert fly(owner(output), np.array([0.0, 12.0, 30.0])) == [12.0, 30.0]
    not_ardupilot = (
        owner("global_position_sensor"),
        owner("odometry", ardupilot=False),
        owner(system_id=None),
    )
    for other in not_ardupilot:
        assert fly(other, np.array([0.0, 12.0, 30.0])) == [] and not other.sent


def test_a_reset_interval_is_positive_seconds_or_never() -> None:
    """``fly --position-reset-every 0`` turns the reset off (None); a negative or infinite
    interval is a clear error naming the field, never a reset after every fix."""
    never = owner()
    never.config = CompanionConfig(position_reset_interval_s=None)
    assert fly(never, np.array([0.0, 12.0, 30.0])) == [] and not never.sent
    for bad in (-1.0, 0.0, math.inf, math.nan):
        with pytest.raises(OrthonavError, match="position_reset_interval_s"):
            CompanionConfig(position_reset_interval_s=bad)
