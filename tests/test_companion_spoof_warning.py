"""The companion warns when the autopilot's own position stays far from the fused visual fixes:
it follows something else (a spoofed GNSS ahead of orthonav's GPS 2), which orthonav's own
positions do not move. With ``on_spoofing="switch-gps"`` it also makes its own GPS the primary;
with ``"switch-source"`` it selects EKF3's ExternalNav source set until the autopilot accepts it."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from orthonav.bench.sitl import SPOOFING_ANSWER
from orthonav.errors import OrthonavError
from orthonav.fusion import InsSample
from orthonav.geo import destination
from orthonav.mavlink import messages
from orthonav.mavlink.companion import APART_RUN, Companion, CompanionConfig, CompanionStats
from orthonav.mavlink.link import dialect
from orthonav.mavlink.telemetry import Receiver
from orthonav.types import Fix, Pose

HOME = (47.0204, -99.1548)


def fix_at(sigma_m: float = 6.0) -> Fix:
    pose = Pose(*HOME, 300.0, 0.0, 0.0, 0.0, *HOME)
    return Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * sigma_m**2)


SPOOFED = destination(*HOME, 45.0, 425.0)


def owner(
    receivers: tuple[tuple[int, float, float], ...] = (), ardupilot: bool = True, **config: Any
) -> SimpleNamespace:
    """The parts of a companion the judgement uses; its warnings and recoveries are collected (a
    recovery, as the companion's events say it, only after a warning), and what it sends."""
    said: list[tuple[str, str]] = []
    sent: list[Any] = []

    def resolved(key: str, text: str, now: float) -> None:
        if said and said[-1][0] == "problem":
            said.append(("resolved", text))

    events = SimpleNamespace(
        problem=lambda key, text, now: said.append(("problem", text)),
        resolved=resolved,
        once=lambda severity, text, now: said.append(("once", text)),
    )
    telemetry = SimpleNamespace(
        ardupilot=ardupilot,
        system_id=1,
        component_id=1,
        receivers=lambda now: [Receiver(*receiver, None) for receiver in receivers],
    )
    companion = SimpleNamespace(
        config=CompanionConfig(**config),
        to_filter=SimpleNamespace(autopilot=None),
        telemetry=telemetry,
        link=SimpleNamespace(send=sent.append, source_system=1),
        stats=CompanionStats(),
        events=events,
        _apart_run=0,
        _answered_s=-np.inf,
        now_s=0.0,  # a fix a second
        said=said,
        sent=sent,
    )
    for method in ("_switch_to_our_gps", "_answer_due", "_select_extnav_set"):
        setattr(companion, method, lambda *a, m=method: getattr(Companion, m)(companion, *a))
    return companion


def judge(companion: SimpleNamespace, apart_m: list[float], sigma_m: float = 6.0) -> list[str]:
    """Fused fixes at home a second apart, the autopilot ``apart_m`` north-east of each: what was
    said, in order."""
    for metres in apart_m:
        companion.now_s += 1.0
        lat, lon = destination(*HOME, 45.0, metres)
        companion.to_filter.autopilot = InsSample(
            companion.now_s, float(lat), float(lon), 0.0, 10.0, 0.0, 300.0
        )
        Companion._judge_autopilot(companion, fix_at(sigma_m), companion.now_s)
    return [kind for kind, _ in companion.said]


def test_a_spoofed_autopilot_is_reported_after_a_run_of_fixes_far_from_it() -> None:
    """425 m away (a SITL spoof) for a run of fixes: a warning naming the distance, then a
    recovery once it agrees again; nothing before the run is long enough."""
    companion = owner()
    assert judge(companion, [425.0] * (APART_RUN - 1)) == []
    assert judge(companion, [425.0, 426.0, 2.0]) == ["problem", "problem", "resolved"]
    assert "425 m from" in companion.said[0][1] and "GNSS spoofed?" in companion.said[0][1]


def test_wrong_matches_and_ordinary_disagreement_raise_nothing() -> None:
    """Within 50 m (a wrong match's 30 m, EKF3 catching up after a gap), within 5 sigma of a
    poor fix, or far away but never for a whole run: no warning."""
    for apart, sigma in ((30.0, 6.0), (49.0, 6.0), (70.0, 15.0)):
        assert judge(owner(), [apart] * 3 * APART_RUN, sigma) == [], (apart, sigma)
    interrupted = [425.0] * (APART_RUN - 1) + [5.0]
    assert judge(owner(), interrupted * 3) == []


def params_set(companion: SimpleNamespace) -> list[tuple[str, float]]:
    return [(m.param_id, m.param_value) for m in companion.sent if m.get_type() == "PARAM_SET"]


def test_switch_gps_makes_the_receiver_near_the_fixes_the_primary_and_repeats_only_while_apart() -> None:
    """GPS 1 spoofed 425 m away, GPS 2 (orthonav's) at the fixes: GPS 2 is made the primary once
    the run is long enough, sent again only as often as the warning while the autopilot stays
    apart."""
    companion = owner(((0, *SPOOFED), (1, *HOME)), on_spoofing="switch-gps")
    judge(companion, [425.0] * APART_RUN)
    assert params_set(companion) == [("GPS_AUTO_SWITCH", 0.0), ("GPS_PRIMARY", 1.0)]
    assert any(kind == "once" and "GPS 2 (orthonav) made primary" in text for kind, text in companion.said)
    judge(companion, [425.0] * 5)  # within the warning's repeat interval: not sent again
    assert len(params_set(companion)) == 2
    judge(companion, [425.0] * 10)
    assert len(params_set(companion)) == 4 and companion.stats.gps_switches == 2


@pytest.mark.parametrize(
    ("receivers", "changes"),
    [
        (((0, *SPOOFED),), {"on_spoofing": "switch-gps"}),  # GPS2_RAW not streamed: which is ours?
        (((0, *HOME), (1, *HOME)), {"on_spoofing": "switch-gps"}),  # both at the fixes
        (((0, *SPOOFED), (1, *HOME)), {}),  # the default: warn only
        (((0, *SPOOFED), (1, *HOME)), {"on_spoofing": "switch-gps", "ardupilot": False}),
    ],
)
def test_nothing_is_switched_where_orthonavs_gps_cannot_be_told_or_was_not_asked_for(
    receivers: tuple, changes: dict
) -> None:
    companion = owner(receivers, **changes)
    judge(companion, [425.0] * 3 * APART_RUN)
    assert params_set(companion) == [] and companion.stats.gps_switches == 0
    assert any("GNSS spoofed?" in text for _, text in companion.said)  # the warning stays


def test_an_unknown_answer_to_spoofing_is_refused_by_name() -> None:
    with pytest.raises(OrthonavError, match="on_spoofing 'land'"):
        CompanionConfig(on_spoofing="land")


def source_requests(companion: SimpleNamespace) -> list[tuple[int, float]]:
    return [(m.command, m.param1) for m in companion.sent if m.get_type() == "COMMAND_LONG"]


def ack(result: int, command: int = 42007, system: int = 1, component: int = 1, target: int = 1) -> Any:
    """A COMMAND_ACK as it arrives: packed by ``system``/``component`` and parsed back."""
    mavlink = dialect()
    sender = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)
    data = mavlink.MAVLink_command_ack_message(command, result, 0, 0, target, 191).pack(sender)
    return mavlink.MAVLink(None).decode(bytearray(data))


def test_the_source_set_request_is_built_as_the_mavlink_definition_says() -> None:
    """MAV_CMD_SET_EKF_SOURCE_SET (42007): a COMMAND_LONG to the autopilot, param1 the set (1-3),
    the rest empty; it survives packing; a set ArduPilot has not is refused by name."""
    mavlink = dialect()
    assert mavlink.enums["MAV_CMD"][42007].name == "MAV_CMD_SET_EKF_SOURCE_SET"
    assert mavlink.enums["MAV_CMD"][42007].param[1] == "Source Set Id."
    for source_set in (1, 2, 3):
        built = messages.set_ekf_source_set((7, 1), source_set)
        msg = mavlink.MAVLink(None).decode(bytearray(built.pack(mavlink.MAVLink(None, 2, 191))))
        assert msg.get_type() == "COMMAND_LONG" and (msg.target_system, msg.target_component) == (7, 1)
        assert (msg.command, msg.param1, msg.confirmation) == (42007, float(source_set), 0)
        assert [msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7] == [0.0] * 6
    for bad in (0, 4):
        with pytest.raises(OrthonavError, match=f"source set {bad}"):
            messages.set_ekf_source_set((1, 1), bad)


def test_switch_source_asks_only_after_the_warning_and_again_with_it_until_accepted() -> None:
    """Nothing before the run of fixes is long enough; then set 3 (as configured) with the
    warning, again only as often as the warning repeats; acks that are not the autopilot's
    answer to it change nothing; once accepted, it is said and never sent again."""
    companion = owner(on_spoofing="switch-source", output="vision", extnav_source_set=3)
    judge(companion, [425.0] * (APART_RUN - 1))
    assert source_requests(companion) == []
    judge(companion, [425.0] * 5)  # the warning, and within its repeat interval
    assert source_requests(companion) == [(42007, 3.0)] and companion.stats.source_switches == 1
    not_the_answer = (
        ack(0, command=400),  # another command's
        ack(0, system=255, component=190),  # the ground station's
        ack(0, target=42),  # the autopilot's answer to someone else
        ack(5),  # in progress
    )
    for msg in not_the_answer:
        Companion._source_set_ack(companion, msg, companion.now_s)
    assert not companion.stats.source_switched and not any("accepted" in text for _, text in companion.said)
    judge(companion, [425.0] * 10)
    assert len(source_requests(companion)) == 2
    Companion._source_set_ack(companion, ack(0), companion.now_s)
    assert companion.stats.source_switched and "the autopilot accepted" in companion.said[-1][1]
    said_once = [text for kind, text in companion.said if kind == "once"]
    for pattern in SPOOFING_ANSWER.values():  # what the SITL benchmark times the answer by
        assert any(pattern.search(text) for text in said_once), pattern
    judge(companion, [425.0] * 40)
    assert len(source_requests(companion)) == 2 and companion.stats.source_switches == 2


def test_a_refused_source_set_is_said_and_asked_again() -> None:
    companion = owner(on_spoofing="switch-source", output="odometry")
    judge(companion, [425.0] * APART_RUN)
    Companion._source_set_ack(companion, ack(2), companion.now_s)  # MAV_RESULT_DENIED
    assert not companion.stats.source_switched
    assert any("refused EKF3 source set 2 (MAV_RESULT 2)" in text for _, text in companion.said)
    judge(companion, [425.0] * 10)
    assert source_requests(companion) == [(42007, 2.0)] * 2


@pytest.mark.parametrize(
    "changes", [{"on_spoofing": "warn"}, {"on_spoofing": "switch-source", "ardupilot": False}]
)
def test_no_source_set_is_asked_for_unless_configured_and_ardupilot(changes: dict) -> None:
    companion = owner(output="vision", **changes)
    judge(companion, [425.0] * 3 * APART_RUN)
    assert source_requests(companion) == [] and companion.stats.source_switches == 0
    assert any("GNSS spoofed?" in text for _, text in companion.said)


@pytest.mark.parametrize(
    ("answer", "output"),
    [
        ("switch-gps", "vision"),
        ("switch-gps", "odometry"),
        ("switch-gps", "global_position_sensor"),
        ("switch-source", "gps_input"),
        ("switch-source", "global_position_sensor"),
    ],
)
def test_an_answer_that_does_not_fit_the_output_is_refused_at_start(answer: str, output: str) -> None:
    with pytest.raises(OrthonavError, match=f"on_spoofing '{answer}' does not fit output '{output}'"):
        CompanionConfig(on_spoofing=answer, output=output)


@pytest.mark.parametrize("source_set", [0, 4, -1])
def test_a_source_set_ardupilot_has_not_is_refused_by_name(source_set: int) -> None:
    with pytest.raises(OrthonavError, match=f"extnav_source_set {source_set}"):
        CompanionConfig(on_spoofing="switch-source", output="vision", extnav_source_set=source_set)


def test_fly_refuses_an_answer_that_does_not_fit_its_output_before_opening_anything(tmp_path: Path) -> None:
    """Named at start, before the map (absent here) or the link is opened."""
    from typer.testing import CliRunner

    from orthonav.cli.main import app

    base = [
        "fly",
        "--map",
        str(tmp_path / "no-map"),
        "--frames",
        str(tmp_path),
        "--connect",
        "udpin:127.0.0.1:1",
    ]
    for output, answer in (("gps_input", "switch-source"), ("vision", "switch-gps")):
        result = CliRunner().invoke(app, [*base, "--output", output, "--on-spoofing", answer])
        assert isinstance(result.exception, OrthonavError), result.output
        assert f"on_spoofing '{answer}' does not fit output '{output}'" in str(result.exception)
    result = CliRunner().invoke(app, [*base, "--output", "vision", "--extnav-source-set", "4"])
    assert isinstance(result.exception, OrthonavError) and "extnav_source_set 4" in str(result.exception)
