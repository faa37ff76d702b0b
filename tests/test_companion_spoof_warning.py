"""The companion warns when the autopilot's own position stays far from the fused visual fixes:
it follows something else (a spoofed GNSS ahead of orthonav's GPS 2), which orthonav's own
positions do not move."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from orthonav.fusion import InsSample
from orthonav.geo import destination
from orthonav.mavlink.companion import APART_RUN, Companion, CompanionConfig
from orthonav.types import Fix, Pose

HOME = (47.0204, -99.1548)


def fix_at(sigma_m: float = 6.0) -> Fix:
    pose = Pose(*HOME, 300.0, 0.0, 0.0, 0.0, *HOME)
    return Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * sigma_m**2)


def owner() -> SimpleNamespace:
    """The parts of a companion the judgement uses; its warnings and recoveries are collected (a
    recovery, as the companion's events say it, only after a warning)."""
    said: list[tuple[str, str]] = []

    def resolved(key: str, text: str, now: float) -> None:
        if said and said[-1][0] == "problem":
            said.append(("resolved", text))

    events = SimpleNamespace(problem=lambda key, text, now: said.append(("problem", text)), resolved=resolved)
    return SimpleNamespace(
        config=CompanionConfig(),
        to_filter=SimpleNamespace(autopilot=None),
        events=events,
        _apart_run=0,
        said=said,
    )


def judge(companion: SimpleNamespace, apart_m: list[float], sigma_m: float = 6.0) -> list[str]:
    """Fused fixes at home, the autopilot ``apart_m`` north of each: what was said, in order."""
    for k, metres in enumerate(apart_m):
        lat, lon = destination(*HOME, 0.0, metres)
        companion.to_filter.autopilot = InsSample(float(k), float(lat), float(lon), 0.0, 10.0, 0.0, 300.0)
        Companion._judge_autopilot(companion, fix_at(sigma_m), float(k))
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
