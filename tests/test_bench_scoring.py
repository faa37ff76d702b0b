"""The scoring every benchmark shares, on handmade errors, sigmas and times whose figures are known."""

from __future__ import annotations

import numpy as np
import pytest

from orthonav.bench.scoring import (
    CHI2_2DOF_95,
    SIGMA_KEYS,
    error_enu_m,
    error_m,
    mean,
    mean_per_frame,
    median,
    nees,
    percentile,
    quantiles,
    rate,
    share,
    sigma_coverage,
    sigma_targets,
    stage_tails,
    within_rates,
    wrong_rate,
)
from orthonav.geo import LocalFrame, destination
from orthonav.types import Fix


def test_rates_are_shares_of_every_frame_not_of_the_fixed_ones() -> None:
    errors = np.array([0.5, 2.0, 4.0, 12.0, 60.0])  # five fixes among ten frames
    assert rate(len(errors), 10) == 0.5
    assert within_rates(errors, 10, (1.0, 5.0, 10.0)) == {
        "within_1m": 0.1,
        "within_5m": 0.3,
        "within_10m": 0.3,
    }
    assert within_rates(errors, 10, (25,), prefix="centre_within_") == {"centre_within_25m": 0.4}
    assert wrong_rate(errors, 10, 10.0) == 0.2 and wrong_rate(errors, 10, 50.0) == 0.1
    assert share((e <= 2.0 for e in errors), 10) == 0.2
    # No frames: every rate 0, never a division by zero.
    assert rate(0, 0) == share([], 0) == wrong_rate(np.array([]), 0, 10.0) == 0.0


def test_quantiles_of_errors_and_times() -> None:
    times = list(range(1, 101))  # 1 .. 100 ms
    tails = quantiles(times)
    assert tails["p50"] == pytest.approx(50.5) and tails["max"] == 100.0
    assert tails["p50"] < tails["p95"] < tails["p99"] < tails["max"]
    assert percentile([1.0, 2.0, 3.0, 4.0], 50, 2) == 2.5 and percentile([], 95) is None
    assert median([3.0, None, 1.0, 2.0]) == 2.0 and median([None]) is None
    assert median([1.0, 2.0], digits=None) == 1.5 and mean([1.0, 2.0, 4.0], 2) == 2.33 and mean([]) is None
    # A stage only some frames reach: its tails over those, and none for a stage never reached.
    timings = [{"total_ms": 10.0, "fine_ms": 4.0}, {"total_ms": 30.0}, {"total_ms": 20.0}]
    out = stage_tails(timings, ("fine_ms", "verify_ms", "total_ms"))
    assert (
        set(out) == {"fine_ms", "total_ms"}
        and out["fine_ms"]["max"] == 4.0
        and out["total_ms"]["p50"] == 20.0
    )
    # Means per frame count a stage a frame skipped as 0, so they add up to the mean total.
    assert mean_per_frame(timings) == {"total_ms": 20.0, "fine_ms": 1.3}


def test_horizontal_error_and_nees_of_known_offsets() -> None:
    truth = (47.0, 8.0)
    rng = np.random.default_rng(0)
    sigma_m = 2.0
    cov = np.diag([sigma_m**2, sigma_m**2])
    values = []
    for _ in range(400):
        east, north = rng.normal(0.0, sigma_m, 2)
        lat, lon = destination(
            *truth, float(np.degrees(np.arctan2(east, north))), float(np.hypot(east, north))
        )
        fix = Fix(True, covariance_enu_m2=cov)
        offset = error_enu_m(LocalFrame(*truth), truth, (float(lat), float(lon)))
        assert error_m(*truth, float(lat), float(lon)) == pytest.approx(np.hypot(east, north), abs=0.01)
        assert offset == pytest.approx([east, north], abs=0.01)
        values.append(nees(fix, offset))
    # Errors drawn from the covariance itself: NEES is chi-square with 2 dof (mean 2, 95 % below 5.99).
    assert 1.7 < np.mean(values) < 2.3
    assert 0.92 < np.mean(np.array(values) <= CHI2_2DOF_95) < 0.98
    # An error along the tight axis of an elongated covariance weighs more than along the loose one.
    stretched = Fix(True, covariance_enu_m2=np.diag([1.0, 16.0]))
    assert nees(stretched, np.array([2.0, 0.0])) == pytest.approx(4.0)
    assert nees(stretched, np.array([0.0, 2.0])) == pytest.approx(0.25)


def test_sigma_coverage_of_known_errors_and_sigmas() -> None:
    errors, sigmas = [0.5, 1.5, 2.5, 3.5, 0.2], [1.0, 1.0, 1.0, 1.0, 1.0]
    nees_values = [e**2 for e in errors]  # a round covariance of sigma 1
    out = sigma_coverage(errors, sigmas, nees_values)
    assert (out["within_1sigma"], out["within_2sigma"], out["within_3sigma"]) == (0.4, 0.6, 0.8)
    assert out["mean_nees"] == pytest.approx(np.mean(nees_values), abs=0.01)
    assert out["p95_m"] == pytest.approx(np.percentile(errors, 95), abs=0.01)
    assert out["sigma_over_p95"] == pytest.approx(1.0 / np.percentile(errors, 95), abs=0.01)
    assert sigma_targets(out) is False  # 80 % within 3 sigma misses the 90 % target
    honest = sigma_coverage([0.5, 1.0, 1.5], [1.0, 1.0, 1.0], [0.25, 1.0, 2.25])
    assert sigma_targets(honest) is True
    # Sigmas far too large for the errors (10 x the p95): covered, but over-cautious.
    assert sigma_targets(sigma_coverage([0.1, 0.2], [5.0, 5.0], [0.01, 0.02])) is False
    empty = sigma_coverage([], [], [])
    assert set(empty) == set(SIGMA_KEYS) and sigma_targets(empty) is None
