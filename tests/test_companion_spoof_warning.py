"""The companion warns when the autopilot's own position stays far from the fused visual fixes:
it follows something else (a spoofed GNSS ahead of orthonav's GPS 2), which orthonav's own
positions do not move. With ``on_spoofing="switch-gps"`` it also makes its own GPS the primary."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from orthonav.errors import OrthonavError
from orthonav.fusion import InsSample
from orthonav.geo import destination
from orthonav.mavlink.companion import APART_RUN, Companion, CompanionConfig
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
        ardupilot=ardupilot, system_id=1, component_id=1, receivers=lambda now: list(receivers)
    )
    companion = SimpleNamespace(
        config=CompanionConfig(**config),
        to_filter=SimpleNamespace(autopilot=None),
        telemetry=telemetry,
        link=SimpleNamespace(send=sent.append),
        stats=SimpleNamespace(gps_switches=0),
        events=events,
        _apart_run=0,
        _gps_switch_s=-np.inf,
        now_s=0.0,  # a fix a second
        said=said,
        sent=sent,
    )
    companion._switch_to_our_gps = lambda *a: Companion._switch_to_our_gps(companion, *a)
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
        (((0, *SPOOFED), (1, *HOME)), {"on_spoofing": "switch-gps", "output": "vision"}),
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
