"""INS drift model and navigation filter: synthetic trajectories, since this is filter maths.

Truth tracks are integrated with the same piecewise-constant acceleration the INS simulator
assumes, so a perfect IMU reproduces them exactly and every error has a known cause.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from orthonav.errors import OrthonavError
from orthonav.fusion import (
    FilterConfig,
    FixOutcome,
    ImuErrorModel,
    InsSample,
    InsSimulator,
    NavFilter,
    NavState,
)
from orthonav.geo import LocalFrame
from orthonav.types import Fix, Pose, positive_definite, worst_sigma

LAT0, LON0 = 47.0, -99.0
FRAME = LocalFrame(LAT0, LON0)  # the frame InsSimulator builds at the same start point
CONSUMER = ImuErrorModel.preset("consumer")
PERFECT = ImuErrorModel.preset("perfect")
FIX_SIGMA_M = 5.0


@dataclass(frozen=True)
class Track:
    """True horizontal motion sampled every dt; accel/rate are constant over each interval."""

    time_s: np.ndarray
    pos_m: np.ndarray
    vel_mps: np.ndarray
    heading_rad: np.ndarray

    @property
    def accel_mps2(self) -> np.ndarray:
        return np.diff(self.vel_mps, axis=0) / np.diff(self.time_s)[:, None]

    @property
    def rate_dps(self) -> np.ndarray:
        return np.degrees(np.diff(self.heading_rad)) / np.diff(self.time_s)

    def fly(self, model: ImuErrorModel, seed: int, vel_error_mps: float = 0.0) -> tuple[InsSimulator, list]:
        """The INS samples an IMU of this grade produces along the track."""
        rng = np.random.default_rng(seed)
        vel = self.vel_mps[0] + rng.normal(0.0, vel_error_mps, 2) if vel_error_mps else self.vel_mps[0]
        heading = math.degrees(self.heading_rad[0])
        ins = InsSimulator(model, rng, self.time_s[0], LAT0, LON0, vel[0], vel[1], heading)
        samples = [ins.sample]
        for k, (accel, rate) in enumerate(zip(self.accel_mps2, self.rate_dps, strict=True)):
            samples.append(ins.step(self.time_s[k + 1], accel[0], accel[1], rate))
        return ins, samples

    def error_m(self, k: int, lat: float, lon: float) -> np.ndarray:
        east, north = FRAME.to_enu(lat, lon)
        return np.array([east, north]) - self.pos_m[k]


def make_track(duration_s: float, dt_s: float, heading_deg, speed_mps) -> Track:
    """Integrate a heading and speed profile (arrays or constants over the sample times)."""
    time_s = np.arange(0.0, duration_s + dt_s / 2, dt_s)
    heading = np.radians(np.broadcast_to(heading_deg, time_s.shape))
    speed = np.broadcast_to(speed_mps, time_s.shape)
    vel = speed[:, None] * np.column_stack([np.sin(heading), np.cos(heading)])
    accel = np.diff(vel, axis=0) / dt_s
    pos = np.zeros_like(vel)
    for k in range(len(time_s) - 1):
        pos[k + 1] = pos[k] + vel[k] * dt_s + 0.5 * accel[k] * dt_s**2
    return Track(time_s, pos, vel, heading)


def curvy_track(duration_s: float, dt_s: float) -> Track:
    """20 m/s with 6 deg/s turns left and right, straight legs in between."""
    time_s = np.arange(0.0, duration_s + dt_s / 2, dt_s)
    rate = np.where(time_s % 40 < 15, 0.0, np.where(time_s % 80 < 40, 6.0, -6.0))
    heading = 30.0 + np.concatenate([[0.0], np.cumsum(rate[:-1] * dt_s)])
    return make_track(duration_s, dt_s, heading, 20.0)


def make_fix(
    track: Track,
    k: int,
    rng: np.random.Generator | None = None,
    offset_m: tuple[float, float] = (0.0, 0.0),
    heading_deg: float | None = None,
) -> Fix:
    """An accepted visual fix of the true position at sample k (plus noise / a deliberate offset)."""
    noise = rng.normal(0.0, FIX_SIGMA_M, 2) if rng is not None else np.zeros(2)
    east, north = track.pos_m[k] + noise + np.asarray(offset_m)
    lat, lon = (float(v) for v in FRAME.to_latlon(east, north))
    heading = math.degrees(track.heading_rad[k]) if heading_deg is None else heading_deg
    pose = Pose(lat, lon, 300.0, heading % 360.0, 0.0, 0.0, lat, lon)
    return Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * FIX_SIGMA_M**2, method="test")


def started_filter(samples: list[InsSample], config: FilterConfig | None = None) -> NavFilter:
    """A filter initialised on the (exact) true start position, INS heading trusted to 1 deg."""
    nav = NavFilter(config or FilterConfig.for_imu(CONSUMER))
    nav.predict(samples[0])
    nav.initialise(samples[0].time_s, LAT0, LON0, sigma_m=2.0, heading_sigma_deg=1.0)
    return nav


def flown_filter(samples: list[InsSample]) -> NavFilter:
    """A started filter propagated through every sample, no fix yet."""
    nav = started_filter(samples)
    for sample in samples[1:]:
        nav.predict(sample)
    return nav


# ---- INS drift model ---------------------------------------------------------------------------


def test_presets_have_units_and_bad_values_are_refused() -> None:
    consumer, tactical = ImuErrorModel.preset("consumer"), ImuErrorModel.preset("tactical")
    assert consumer.accel_bias_mps2 > tactical.accel_bias_mps2 > 0.0
    assert consumer.gyro_bias_dps > tactical.gyro_bias_dps > 0.0
    assert all(v == 0.0 for v in vars(ImuErrorModel.preset("perfect")).values())
    with pytest.raises(OrthonavError, match="consumer, perfect, tactical"):
        ImuErrorModel.preset("military")
    with pytest.raises(OrthonavError, match="accel_bias_mps2"):
        ImuErrorModel(accel_bias_mps2=-1.0)


def test_perfect_imu_reproduces_the_true_track() -> None:
    track = curvy_track(120.0, 0.5)
    _, samples = track.fly(PERFECT, seed=1)
    last = samples[-1]
    assert np.linalg.norm(track.error_m(-1, last.lat, last.lon)) < 1e-3
    assert abs(_angle_diff(last.heading_deg, math.degrees(track.heading_rad[-1]))) < 1e-9
    assert np.allclose([last.vel_east_mps, last.vel_north_mps], track.vel_mps[-1], atol=1e-9)


def test_consumer_ins_drift_grows_as_its_bias_predicts() -> None:
    """Straight and level: only accelerometer bias (+walk, noise) acts, error ~ b t^2 / 2 per axis."""
    track = make_track(120.0, 1.0, 45.0, 20.0)
    errors = np.array(
        [[np.linalg.norm(track.error_m(k, s[k].lat, s[k].lon)) for k in (10, 120)] for s in _flights(track)]
    )
    rms_10, rms_120 = np.sqrt(np.mean(errors**2, axis=0))
    m, t = CONSUMER, 120.0
    per_axis = math.hypot(  # bias, bias walk, velocity random walk
        0.5 * m.accel_bias_mps2 * t**2,
        m.accel_bias_walk_mps2_per_sqrt_s * t**2.5 / math.sqrt(20.0),
        m.accel_noise_mps_per_sqrt_s * t**1.5 / math.sqrt(3.0),
    )
    assert rms_120 > 50.0 * rms_10
    assert 0.7 < rms_120 / (math.sqrt(2.0) * per_axis) < 1.3


def _flights(track: Track) -> list[list[InsSample]]:
    return [track.fly(CONSUMER, seed)[1] for seed in range(30)]


def test_accel_scale_factor_stretches_distance_along_the_acceleration() -> None:
    """Accelerating north at 2 m/s^2: a scale error s puts the INS s * a t^2 / 2 ahead."""
    track = make_track(20.0, 0.5, 0.0, 10.0 + 2.0 * np.arange(0.0, 20.25, 0.5))
    ins, samples = track.fly(ImuErrorModel(accel_scale_factor_ppm=10_000.0), seed=3)
    scale = ins.errors.accel_scale[0]
    assert abs(scale) > 1e-3
    error = track.error_m(-1, samples[-1].lat, samples[-1].lon)
    assert error[1] == pytest.approx(scale * 0.5 * 2.0 * 20.0**2, rel=1e-4)
    assert abs(error[0]) < 1e-3


def test_biases_push_the_ins_the_right_way() -> None:
    """Flying east: forward bias -> ahead (east), right bias -> south; gyro bias -> heading drift."""
    track = make_track(30.0, 0.5, 90.0, 15.0)
    ins, samples = track.fly(ImuErrorModel(accel_bias_mps2=0.1), seed=4)
    forward, right = ins.errors.accel_bias_body_mps2
    error = track.error_m(-1, samples[-1].lat, samples[-1].lon)
    assert error[0] == pytest.approx(0.5 * forward * 30.0**2, rel=1e-6)
    assert error[1] == pytest.approx(-0.5 * right * 30.0**2, rel=1e-6)
    ins, samples = track.fly(ImuErrorModel(gyro_bias_dps=0.05), seed=4)
    heading_error = _angle_diff(samples[-1].heading_deg, 90.0)
    assert heading_error == pytest.approx(ins.errors.gyro_bias_dps * 30.0, rel=1e-9)
    assert np.linalg.norm(track.error_m(-1, samples[-1].lat, samples[-1].lon)) < 1e-3  # no accel: no effect


def test_bad_ins_input_is_refused() -> None:
    ins = InsSimulator(PERFECT, np.random.default_rng(0), 5.0, LAT0, LON0, 0.0, 10.0, 0.0)
    with pytest.raises(OrthonavError, match="time must increase"):
        ins.step(5.0, 0.0, 0.0, 0.0)
    with pytest.raises(OrthonavError, match="finite"):
        ins.step(6.0, math.nan, 0.0, 0.0)
    with pytest.raises(OrthonavError, match="INS sample"):
        NavFilter().predict(InsSample(0.0, LAT0, LON0, math.nan, 0.0, 0.0))


# ---- filter: covariance, gating ------------------------------------------------------------------


def test_covariance_grows_without_fixes_and_a_fix_shrinks_it() -> None:
    track = curvy_track(60.0, 0.5)
    _, samples = track.fly(CONSUMER, seed=5)
    nav = started_filter(samples)
    sigmas = [nav.predict(sample).sigma_m for sample in samples[1:]]
    assert np.all(np.diff(sigmas) > 0.0)
    assert nav.state().status == "dead reckoning" and nav.state().since_fix_s is None
    outcome = nav.update(make_fix(track, len(samples) - 1), samples[-1].time_s)
    assert outcome.accepted and outcome.reason == "accepted"
    state = nav.state()
    assert state.sigma_m < min(sigmas[-1], FIX_SIGMA_M)
    assert state.status == "fixed" and state.since_fix_s == 0.0
    assert np.linalg.norm(track.error_m(-1, state.lat, state.lon)) < 3.0 * state.sigma_m


def test_outlier_is_rejected_and_logged_while_good_fixes_keep_being_accepted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    track = curvy_track(60.0, 0.5)
    _, samples = track.fly(CONSUMER, seed=6)
    nav, rng = started_filter(samples), np.random.default_rng(6)
    outcomes = {}
    with caplog.at_level(logging.INFO, logger="orthonav.fusion"):
        for k, sample in enumerate(samples[1:], start=1):
            nav.predict(sample)
            if k % 10 == 0:
                fix = make_fix(track, k, rng, offset_m=(500.0, 0.0) if k == 60 else (0.0, 0.0))
                outcomes[k] = nav.update(fix, sample.time_s)
    outlier = outcomes.pop(60)
    assert not outlier.accepted
    assert outlier.reason == f"mahalanobis {outlier.mahalanobis:.2f} > {nav.config.gate:.2f}"
    assert outlier.mahalanobis > 20.0 and outlier.innovation_east_m > 400.0
    assert all(o.accepted for o in outcomes.values())
    assert any("fix rejected: mahalanobis" in r.getMessage() for r in caplog.records)
    assert np.linalg.norm(track.error_m(-1, nav.state().lat, nav.state().lon)) < 3.0 * nav.state().sigma_m


def test_unusable_fixes_are_rejected_with_their_reason() -> None:
    track = make_track(10.0, 0.5, 0.0, 10.0)
    _, samples = track.fly(PERFECT, seed=0)
    assert NavFilter().update(make_fix(track, 0), 0.0).reason == "no INS sample yet"
    nav = started_filter(samples[:5])
    for sample in samples[1:5]:
        nav.predict(sample)
    good = make_fix(track, 4)
    cases = {
        "localizer: too few inliers (12 < 25)": Fix(False, reason="too few inliers (12 < 25)"),
        "no covariance": replace(good, covariance_enu_m2=None),
        "covariance or position not finite": replace(good, covariance_enu_m2=np.full((2, 2), np.nan)),
        "covariance not positive definite": replace(good, covariance_enu_m2=-np.eye(2)),
        "from the future: captured 3.00 s after the newest INS sample": good,
    }
    for reason, fix in cases.items():
        outcome = nav.update(fix, 5.0 if reason.startswith("from") else 2.0)
        assert (outcome.accepted, outcome.reason) == (False, reason)
    assert nav.state().status == "dead reckoning"


def test_heading_outlier_is_not_used_but_the_position_is() -> None:
    track = make_track(10.0, 0.5, 0.0, 10.0)
    _, samples = track.fly(PERFECT, seed=0)
    nav = flown_filter(samples)
    outcome = nav.update(make_fix(track, 20, heading_deg=180.0), samples[-1].time_s)
    assert outcome.accepted and "heading 180.0 deg off" in outcome.reason and "not used" in outcome.reason
    assert abs((nav.state().heading_deg + 180.0) % 360.0 - 180.0) < 1e-6


def _accelerating_flight() -> tuple[Track, list[InsSample], ImuErrorModel]:
    """North at 10 m/s, then +2 m/s^2 from 20 s; a 0.66 deg/s gyro bias: 26 deg off after 40 s."""
    time_s = np.arange(0.0, 40.25, 0.5)
    track = make_track(40.0, 0.5, 0.0, np.where(time_s < 20.0, 10.0, 10.0 + 2.0 * (time_s - 20.0)))
    model = ImuErrorModel(gyro_bias_dps=0.5)
    return track, track.fly(model, seed=13)[1], model


def test_heading_fixes_undo_the_drift_a_heading_error_causes_while_accelerating() -> None:
    """Heading fixes until 20 s pin the gyro bias; the filter then dead-reckons the acceleration."""
    track, samples, model = _accelerating_flight()
    nav = started_filter(samples, FilterConfig.for_imu(model, heading_fix_sigma_deg=0.2))
    for k, sample in enumerate(samples[1:], start=1):
        nav.predict(sample)
        if k % 10 == 0 and k <= 40:
            assert nav.update(make_fix(track, k), sample.time_s).accepted
    ins_error = np.linalg.norm(track.error_m(-1, samples[-1].lat, samples[-1].lon))
    filter_error = np.linalg.norm(track.error_m(-1, nav.state().lat, nav.state().lon))
    assert ins_error > 100.0 and filter_error < 0.05 * ins_error
    assert abs(_angle_diff(nav.state().heading_deg, 0.0)) < 0.2


def test_position_fixes_alone_reveal_the_heading_error_once_accelerating() -> None:
    """Without heading measurements the heading is observable only through the acceleration."""
    track, samples, model = _accelerating_flight()
    nav = started_filter(samples, FilterConfig.for_imu(model, heading_fix_sigma_deg=None))
    for k, sample in enumerate(samples[1:], start=1):
        nav.predict(sample)
        if k % 5 == 0:
            assert nav.update(make_fix(track, k), sample.time_s).accepted
    assert abs(_angle_diff(samples[-1].heading_deg, 0.0)) > 20.0
    state = nav.state()
    assert abs(_angle_diff(state.heading_deg, 0.0)) < max(1.0, 3.0 * state.heading_sigma_deg)
    assert state.heading_sigma_deg < 2.0


# ---- filter: heading wrap ------------------------------------------------------------------------


def _still(time_s: float, heading: float) -> InsSample:
    return InsSample(time_s, LAT0, LON0, 0.0, 0.0, heading)


def _heading_update(ins_heading_deg: float, fix_heading_deg: float) -> NavState:
    nav = NavFilter(FilterConfig.for_imu(PERFECT, heading_fix_sigma_deg=2.0))
    nav.predict(_still(0.0, ins_heading_deg))
    nav.initialise(0.0, LAT0, LON0, sigma_m=2.0, heading_sigma_deg=5.0)
    nav.predict(_still(1.0, ins_heading_deg))
    pose = Pose(LAT0, LON0, 300.0, fix_heading_deg, 0.0, 0.0, LAT0, LON0)
    assert nav.update(Fix(True, pose=pose, covariance_enu_m2=np.eye(2)), 1.0).accepted
    return nav.state()


def _angle_diff(a: float, b: float) -> float:
    return (a - b + 180.0) % 360.0 - 180.0


def test_heading_359_and_1_degree_are_2_degrees_apart() -> None:
    state = _heading_update(359.0, 1.0)
    assert 0.0 <= state.heading_deg < 360.0
    assert abs(_angle_diff(state.heading_deg, 359.0 + 2.0 * 25.0 / 29.0)) < 1e-6  # 5 deg prior, 2 deg fix
    assert state.heading_sigma_deg < 2.0


@settings(max_examples=30, deadline=None)
@given(st.floats(0.0, 360.0, exclude_max=True), st.floats(-10.0, 10.0).filter(lambda d: abs(d) > 0.01))
def test_heading_update_moves_towards_the_fix_across_north(ins_heading: float, offset: float) -> None:
    fix_heading = (ins_heading + offset) % 360.0
    state = _heading_update(ins_heading, fix_heading)
    moved = _angle_diff(state.heading_deg, ins_heading)
    assert 0.0 <= state.heading_deg < 360.0
    assert np.sign(moved) == np.sign(offset) and abs(moved) < abs(offset)


# ---- filter: latency ----------------------------------------------------------------------------


@lru_cache(maxsize=1)
def _latency_flight() -> tuple[Track, tuple[InsSample, ...]]:
    track = curvy_track(30.0, 0.5)
    return track, tuple(track.fly(CONSUMER, seed=7)[1])


def _fly_with_fixes(arrivals: dict[int, list[tuple[Fix, float]]]) -> NavFilter:
    """Feed every INS sample; after sample k, the fixes (fix, capture time) that arrive then."""
    _, samples = _latency_flight()
    nav = started_filter(list(samples))
    for k, sample in enumerate(samples[1:], start=1):
        nav.predict(sample)
        for fix, capture_time_s in arrivals.get(k, []):
            assert nav.update(fix, capture_time_s).accepted
    return nav


def _assert_same_state(a: NavState, b: NavState) -> None:
    east_a, north_a = FRAME.to_enu(a.lat, a.lon)
    east_b, north_b = FRAME.to_enu(b.lat, b.lon)
    assert math.hypot(east_a - east_b, north_a - north_b) < 1e-6
    assert abs(_angle_diff(a.heading_deg, b.heading_deg)) < 1e-6
    assert np.allclose([a.vel_east_mps, a.vel_north_mps], [b.vel_east_mps, b.vel_north_mps], atol=1e-6)
    assert np.allclose(a.covariance_enu_m2, b.covariance_enu_m2, atol=1e-6)
    assert a.heading_sigma_deg == pytest.approx(b.heading_sigma_deg, abs=1e-6)


@settings(max_examples=20, deadline=None)
@given(st.integers(12, 30), st.sampled_from([0.0, 0.3, 0.5, 0.9]), st.integers(1, 16))
def test_late_fix_ends_in_the_same_state_as_on_time(k: int, fraction: float, delay: int) -> None:
    """A fix captured at sample k (+fraction of a step) arriving `delay` samples late, across a later fix."""
    track, samples = _latency_flight()
    rng = np.random.default_rng(k)
    early, later = make_fix(track, 10, rng), make_fix(track, k + 6, rng)
    fix, capture = make_fix(track, k, rng), samples[k].time_s + 0.5 * fraction
    on_time_k = k if fraction == 0.0 else k + 1
    common = {10: [(early, samples[10].time_s)]}
    on_time = _fly_with_fixes(
        {**common, on_time_k: [(fix, capture)], k + 6: [(later, samples[k + 6].time_s)]}
    )
    late_k = on_time_k + delay
    late_arrivals = {**common, k + 6: [(later, samples[k + 6].time_s)]}
    late_arrivals.setdefault(late_k, []).append((fix, capture))
    late = _fly_with_fixes(late_arrivals)
    _assert_same_state(on_time.state(), late.state())
    assert late.state().since_fix_s == pytest.approx(samples[-1].time_s - samples[k + 6].time_s)


def test_fix_older_than_the_history_is_stale() -> None:
    track = make_track(30.0, 0.5, 0.0, 10.0)
    _, samples = track.fly(CONSUMER, seed=8)
    nav = started_filter(samples, FilterConfig.for_imu(CONSUMER, history_s=10.0))
    for sample in samples[1:]:
        nav.predict(sample)
    outcome = nav.update(make_fix(track, 30), 15.0)
    assert not outcome.accepted
    assert outcome.reason == "stale: captured 15.0 s ago, history holds 10.0 s"
    assert outcome.latency_s == 15.0
    in_time = nav.update(make_fix(track, 42), 21.0)
    assert in_time.accepted and in_time.latency_s == 9.0


# ---- filter: lost, re-initialisation ------------------------------------------------------------


def test_lost_filter_reinitialises_from_two_consistent_fixes_never_from_an_outlier() -> None:
    """The INS started 300 m from the truth, so the error estimate is large when the filter gets lost."""
    track, truth_offset_m = curvy_track(120.0, 0.5), np.array([300.0, -150.0])
    _, samples = track.fly(CONSUMER, seed=9)
    nav = NavFilter(FilterConfig.for_imu(CONSUMER, reinit_after_s=60.0))
    nav.predict(samples[0])
    nav.initialise(0.0, *(float(v) for v in FRAME.to_latlon(*truth_offset_m)), sigma_m=2.0)
    rng = np.random.default_rng(9)
    arrivals = {40: (0.0, 0.0), 200: (500.0, 0.0), 210: (0.0, 0.0), 220: (0.0, -500.0), 230: (0.0, 0.0)}
    outcomes, statuses, states = {}, {}, {}
    for k, sample in enumerate(samples[1:], start=1):
        statuses[k] = nav.predict(sample).status
        if k in arrivals:
            fix = make_fix(track, k, rng, offset_m=truth_offset_m + arrivals[k])
            outcomes[k], states[k] = nav.update(fix, sample.time_s), nav.state()
    assert outcomes[40].accepted and statuses[60] == "fixed" and statuses[100] == "dead reckoning"
    assert statuses[160] == "dead reckoning" and statuses[162] == "lost"  # 60 s after the fix at 20 s
    assert outcomes[200].reason == "lost: held for re-initialisation, no earlier fix to pair with"
    for k in (210, 220):
        assert not outcomes[k].accepted and outcomes[k].reason.startswith("lost: held for re-initialisation")
        assert outcomes[k].mahalanobis > 10.0 and statuses[k + 5] == "lost"
    assert outcomes[230].accepted and outcomes[230].reason == "reinitialised"
    assert states[230].status == "fixed" and states[230].sigma_m < FIX_SIGMA_M < states[220].sigma_m
    state = nav.state()
    assert np.linalg.norm(track.error_m(-1, state.lat, state.lon) - truth_offset_m) < 3.0 * state.sigma_m


def test_a_fix_vaguer_than_a_lost_filter_is_refused_and_widens_nothing() -> None:
    """A pose whose covariance claims hundreds of kilometres tells nothing (taken by a lost
    filter it would re-initialise it that wide). Refused, the filter keeps its width and the next
    sane fix is fused."""
    track = curvy_track(60.0, 0.5)
    _, samples = track.fly(CONSUMER, seed=5)
    nav = started_filter(samples, FilterConfig.for_imu(CONSUMER, fix_correlation_s=10.0))
    rng = np.random.default_rng(5)
    for sample in samples[1:41]:
        nav.predict(sample)
    before = nav.state().sigma_m
    for vague_sigma_m in (2.0 * nav.config.lost_sigma_m, 414_764.0):
        vague = replace(make_fix(track, 40, rng), covariance_enu_m2=np.eye(2) * vague_sigma_m**2)
        outcome = nav.update(vague, samples[40].time_s)
        assert not outcome.accepted and "vaguer than a lost filter" in outcome.reason, outcome.reason
        assert nav.state().sigma_m == pytest.approx(before)
    assert nav.update(make_fix(track, 40, rng), samples[40].time_s).accepted
    assert nav.state().sigma_m < before


def test_a_correlated_fix_vaguer_than_unpinned_fixes_are_taken_never_widens_the_filter() -> None:
    """A fix sharing its error with those just fused (fix_correlation_s) leaves the position known
    no better than its own covariance, except where it claims more than unpinned_max_sigma_m:
    raised to such a fix's width, every right fix after it could be refused as a correlation pose
    under a wide prediction, so the filter keeps its width. A sharp correlated fix still holds
    the filter at its own width, not narrower."""
    track = curvy_track(60.0, 0.5)
    _, samples = track.fly(CONSUMER, seed=6)
    nav = started_filter(samples, FilterConfig.for_imu(CONSUMER, fix_correlation_s=10.0))
    rng = np.random.default_rng(6)
    for k, sample in enumerate(samples[1:45], start=1):
        nav.predict(sample)
        if k in (40, 42):
            assert nav.update(make_fix(track, k, rng), sample.time_s).accepted
    sharp = nav.state().sigma_m
    assert sharp == pytest.approx(FIX_SIGMA_M, rel=0.2)  # two correlated fixes: no better than one
    for vague_sigma_m in (30.0 * FIX_SIGMA_M, 0.9 * nav.config.lost_sigma_m):
        vague = replace(make_fix(track, 44, rng), covariance_enu_m2=np.eye(2) * vague_sigma_m**2)
        assert nav.update(vague, samples[44].time_s).accepted
        assert nav.state().sigma_m <= sharp * 1.01, (vague_sigma_m, nav.state().sigma_m)


def test_a_run_of_fixes_sharing_one_bias_never_leaves_the_filter_claiming_less_than_its_error() -> None:
    """Fixes over the same ground share their error: a run of them placed 35 m east of the truth,
    each claiming 20 m, pulls the estimate all the way over. The filter must then claim at least
    as much as a fix does, or it sends a position beyond 3 sigma: held at the sharp fixes' width
    before the run, it would."""
    track = curvy_track(60.0, 0.5)
    _, samples = track.fly(CONSUMER, seed=7)
    nav = started_filter(samples, FilterConfig.for_imu(CONSUMER, fix_correlation_s=10.0))
    rng = np.random.default_rng(7)
    biased_sigma_m = 20.0
    for k, sample in enumerate(samples[1:85], start=1):
        nav.predict(sample)
        if k in (40, 42):
            assert nav.update(make_fix(track, k, rng), sample.time_s).accepted
        elif k > 42:
            fix = replace(
                make_fix(track, k, offset_m=(35.0, 0.0)), covariance_enu_m2=np.eye(2) * biased_sigma_m**2
            )
            nav.update(fix, sample.time_s)
            state = nav.state()
            error_m = float(np.hypot(*track.error_m(k, state.lat, state.lon)))
            assert error_m <= 3.0 * state.sigma_m, (k, error_m, state.sigma_m)
    assert float(np.hypot(*track.error_m(84, state.lat, state.lon))) > 25.0  # the run did pull it over


UNPINNED = {"inliers": 0.0, "verify_margin": 0.02}  # a correlation pose its verification singles out


def test_a_wide_prediction_takes_no_fix_that_nothing_pins_however_many_agree() -> None:
    """Dead reckoning past the limit: correlation poses on a twin 200 m away agree frame after
    frame and are all refused; the same poses at the truth are fused where the prediction is
    narrow enough to check them, and a pose keypoints pin is fused at once after the gap; after
    a new start, the first fixes are weighed at the sigma it gave."""
    track = curvy_track(240.0, 0.5)
    _, samples = track.fly(CONSUMER, seed=4)
    nav, rng = started_filter(samples), np.random.default_rng(4)
    limit = nav.config.unpinned_max_sigma_m
    outcomes = {}
    for k, sample in enumerate(samples[1:], start=1):
        nav.predict(sample)
        if k % 20 == 0 and k <= 100:  # fixes every 10 s while the prediction is narrow
            fix = replace(make_fix(track, k, rng), quality=dict(UNPINNED))
            outcomes[k] = (nav.state().sigma_m, nav.update(fix, sample.time_s))
        if k > 100 and nav.state().sigma_m > 2.0 * limit:
            break
    assert all(sigma <= limit and outcome.accepted for sigma, outcome in outcomes.values()), outcomes
    before = nav.state()
    assert before.sigma_m > limit, "the prediction never grew past the limit"
    for twin_k in range(k + 1, k + 9):
        nav.predict(samples[twin_k])
        twin = replace(make_fix(track, twin_k, offset_m=(200.0, 0.0)), quality=dict(UNPINNED))
        outcome = nav.update(twin, samples[twin_k].time_s)
        assert not outcome.accepted and "no keypoints pin" in outcome.reason, outcome.reason
    assert nav.state().sigma_m > limit
    pinned = replace(make_fix(track, twin_k, rng), quality={"inliers": 40.0})
    assert nav.update(pinned, samples[twin_k].time_s).accepted
    assert nav.state().sigma_m < limit
    # A new start (an autopilot's reboot) at a wide sigma takes its first fixes as they come.
    restart_k = twin_k + 1
    nav.predict(samples[restart_k])
    nav.initialise(samples[restart_k].time_s, LAT0, LON0, sigma_m=4.0 * limit)
    first = replace(make_fix(track, restart_k, rng), quality=dict(UNPINNED))
    assert "no keypoints pin" not in nav.update(first, samples[restart_k].time_s).reason
    with pytest.raises(OrthonavError, match="unpinned_max_sigma_m"):
        FilterConfig(unpinned_max_sigma_m=0.0)


@pytest.mark.parametrize("seed", range(3))
def test_uninitialised_filter_starts_from_the_first_consistent_pair(seed: int) -> None:
    """Fixes 20 s apart: the pair must allow for the INS drift in between (1 m/s velocity error)."""
    track = curvy_track(30.0, 0.5)
    _, samples = track.fly(CONSUMER, seed=seed, vel_error_mps=1.0)
    nav, rng = NavFilter(FilterConfig.for_imu(CONSUMER)), np.random.default_rng(seed + 1000)
    assert nav.state().status == "uninitialised" and math.isnan(nav.state().lat)
    assert samples[0].time_s > nav.state().time_s  # what a caller checks before predict()
    for k, sample in enumerate(samples):
        assert nav.predict(sample).status == ("uninitialised" if k <= 44 else "fixed")
        if k in (4, 44):
            outcome = nav.update(make_fix(track, k, rng), sample.time_s)
            assert outcome.accepted == (k == 44)
    assert outcome.reason == "reinitialised"
    assert np.linalg.norm(track.error_m(-1, nav.state().lat, nav.state().lon)) < 3.0 * nav.state().sigma_m


def test_initialise_refuses_bad_input_and_works_before_the_first_ins_sample() -> None:
    nav = NavFilter()
    nav.initialise(0.0, LAT0, LON0, sigma_m=3.0)
    assert nav.predict(_still(0.0, 10.0)).status == "dead reckoning"
    assert nav.state().sigma_m == pytest.approx(3.0)
    with pytest.raises(OrthonavError, match="sigma_m"):
        nav.initialise(0.0, LAT0, LON0, sigma_m=0.0)
    with pytest.raises(OrthonavError, match="within the INS history"):
        nav.initialise(-100.0, LAT0, LON0, sigma_m=3.0)


def test_ins_clock_going_back_restarts_the_history_and_keeps_the_estimate() -> None:
    nav = NavFilter()
    nav.predict(_still(100.0, 10.0))
    nav.initialise(100.0, LAT0, LON0, sigma_m=3.0)
    before = nav.predict(_still(101.0, 10.0))
    after = nav.predict(_still(1.0, 10.0))
    assert after.time_s == 1.0 and after.status == before.status
    assert after.sigma_m == pytest.approx(before.sigma_m)


# ---- filter: honest covariance -------------------------------------------------------------------


def _chi2_quantile(p: float, dof: int) -> float:
    """Wilson-Hilferty approximation (within 0.1% for 100 degrees of freedom)."""
    z = {0.005: -2.5758293, 0.995: 2.5758293}[p]
    return dof * (1.0 - 2.0 / (9.0 * dof) + z * math.sqrt(2.0 / (9.0 * dof))) ** 3


def _nees_run(seed: int, track: Track, config: FilterConfig) -> tuple[np.ndarray, int]:
    """Position NEES at every INS sample of one run with noisy fixes every 5 s; and rejections."""
    rng = np.random.default_rng(seed + 1000)  # independent of the IMU's own random stream
    _, samples = track.fly(CONSUMER, seed, vel_error_mps=config.initial_velocity_sigma_mps)
    nav = NavFilter(config)
    nav.predict(samples[0])
    east, north = rng.normal(0.0, FIX_SIGMA_M, 2)
    lat, lon = FRAME.to_latlon(east, north)
    nav.initialise(0.0, float(lat), float(lon), sigma_m=FIX_SIGMA_M, heading_sigma_deg=0.5)
    nees, rejected = [], 0
    for k, sample in enumerate(samples[1:], start=1):
        state = nav.predict(sample)
        if k % 10 == 0:
            heading = math.degrees(track.heading_rad[k]) + rng.normal(0.0, config.heading_fix_sigma_deg)
            rejected += not nav.update(make_fix(track, k, rng, heading_deg=heading), sample.time_s).accepted
            state = nav.state()
        error = track.error_m(k, state.lat, state.lon)
        nees.append(error @ np.linalg.solve(state.covariance_enu_m2, error))
    return np.array(nees), rejected


def test_monte_carlo_position_nees_is_within_the_chi_square_band() -> None:
    """50 consumer-IMU runs with 5 m fixes every 5 s: the covariance is neither optimistic nor lazy."""
    runs = 50
    track, config = curvy_track(60.0, 0.5), FilterConfig.for_imu(CONSUMER)
    results = [_nees_run(seed, track, config) for seed in range(runs)]
    average_nees = np.mean([nees for nees, _ in results], axis=0)
    low, high = (_chi2_quantile(p, 2 * runs) / runs for p in (0.005, 0.995))
    inside = np.mean((average_nees > low) & (average_nees < high))
    assert inside >= 0.95, (low, high, np.round(average_nees, 2))
    assert low < average_nees.mean() < high
    assert sum(rejected for _, rejected in results) <= 3  # gate at 0.999 on 600 good fixes


def test_outcome_and_state_serialise_to_strict_json() -> None:
    track = make_track(5.0, 0.5, 0.0, 10.0)
    _, samples = track.fly(PERFECT, seed=0)
    nav = flown_filter(samples)
    outcome = nav.update(make_fix(track, 10), 5.0)
    record = json.loads(
        json.dumps({"fix": outcome.to_dict(), "state": nav.state().to_dict()}, allow_nan=False)
    )
    assert record["fix"]["accepted"] and record["state"]["status"] == "fixed"
    assert record["state"]["sigma_m"] == pytest.approx(nav.state().sigma_m, abs=1e-3)
    json.dumps(NavFilter().state().to_dict(), allow_nan=False)
    json.dumps(NavFilter().update(make_fix(track, 0), 0.0).to_dict(), allow_nan=False)


# ---- filter: a prediction gone wrong, a held velocity ------------------------------------------


def _ins_reporting(track: Track, vel_mps: np.ndarray, sigma_mps: np.ndarray | None = None) -> list[InsSample]:
    """An INS that reports ``vel_mps`` (with ``sigma_mps``) along the track and integrates it from
    the true start (the trapezoid, exact for the track's own piecewise-constant acceleration)."""
    steps = np.diff(track.time_s)[:, None] * (vel_mps[1:] + vel_mps[:-1]) / 2.0
    pos = track.pos_m[0] + np.vstack([np.zeros(2), np.cumsum(steps, axis=0)])
    sigma = np.zeros(len(track.time_s)) if sigma_mps is None else sigma_mps
    samples = []
    for k, t in enumerate(track.time_s):
        lat, lon = (float(v) for v in FRAME.to_latlon(*pos[k]))
        heading = math.degrees(track.heading_rad[k])
        samples.append(
            InsSample(float(t), lat, lon, *map(float, vel_mps[k]), heading, 300.0, float(sigma[k]))
        )
    return samples


def _between(track: Track, start_s: float, end_s: float) -> np.ndarray:
    return (track.time_s >= start_s) & (track.time_s < end_s)


def _fly_fixed_at(
    track: Track,
    samples: list[InsSample],
    fixed: set[int],
    offsets: dict[int, tuple[float, float]] | None = None,
) -> tuple[dict[int, FixOutcome], dict[int, NavState]]:
    """A started filter through ``samples``, a 5 m fix of the truth at the samples ``fixed``
    (``offsets`` moves some); the outcomes and the state after every sample."""
    nav, rng = started_filter(samples), np.random.default_rng(11)
    outcomes, states = {}, {}
    for k, sample in enumerate(samples[1:], start=1):
        nav.predict(sample)
        if k in fixed:
            offset = (offsets or {}).get(k, (0.0, 0.0))
            outcomes[k] = nav.update(make_fix(track, k, rng, offset_m=offset), sample.time_s)
        states[k] = nav.state()
    return outcomes, states


def _beyond_3_sigma(track: Track, states: dict[int, NavState], after_k: int = 0) -> list[int]:
    return [
        k
        for k, state in states.items()
        if k >= after_k and np.linalg.norm(track.error_m(k, state.lat, state.lon)) > 3.0 * state.sigma_m
    ]


def test_fixes_that_agree_with_each_other_but_not_the_prediction_reset_the_filter(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """An INS velocity 30 m/s off for 6 s with nothing to say so (a fault that got through): the
    right fixes come after it, are gated out, and three in a row that agree reset the filter."""
    track = make_track(40.0, 0.1, 90.0, 20.0)
    samples = _ins_reporting(track, track.vel_mps + np.outer(_between(track, 10.0, 16.0), [0.0, 30.0]))
    fixed = set(range(0, 90, 5)) | set(range(170, len(samples), 5))  # a fix every 0.5 s but 9-17 s
    with caplog.at_level(logging.WARNING, logger="orthonav.fusion"):
        outcomes, states = _fly_fixed_at(track, samples, fixed)
    later = sorted(k for k in outcomes if k >= 170)
    first = outcomes[later[0]]
    assert not first.accepted and first.innovation_north_m < -150.0  # 180 m off: gated out
    assert [outcomes[k].reset for k in later[:4]] == [False, False, True, False]
    assert "reset: 3 fixes in a row agree with each other" in outcomes[later[2]].reason
    assert all(outcomes[k].accepted for k in later[2:])
    assert any("filter reset: 3 fixes in a row" in r.getMessage() for r in caplog.records)
    assert _beyond_3_sigma(track, states, later[2]) == []
    assert np.linalg.norm(track.error_m(later[-1], states[later[-1]].lat, states[later[-1]].lon)) < 5.0


def test_outliers_in_a_row_that_disagree_with_each_other_never_reset_the_filter() -> None:
    track = make_track(30.0, 0.1, 90.0, 20.0)
    samples = _ins_reporting(track, track.vel_mps)
    outliers = {100: (500.0, 0.0), 105: (-500.0, 0.0), 110: (0.0, 500.0), 115: (0.0, -500.0)}
    outcomes, states = _fly_fixed_at(track, samples, set(range(0, len(samples), 5)), outliers)
    assert [outcomes[k].accepted for k in outliers] == [False] * 4
    assert not any(o.reset for o in outcomes.values())
    assert all(outcomes[k].accepted for k in outcomes if k not in outliers)
    assert _beyond_3_sigma(track, states) == []


def test_a_held_velocity_widens_the_position_as_the_vehicle_could_have_moved() -> None:
    """The INS velocity held at its last value for 6 s while the vehicle accelerates north at
    3 m/s2 (a third of a copter's limit): said to be uncertain, the filter's 3 sigma covers the truth."""
    t = np.arange(0.0, 30.0 + 0.05, 0.1)
    north = 3.0 * np.clip(t - 10.0, 0.0, 6.0)
    track = make_track(30.0, 0.1, np.degrees(np.arctan2(20.0, north)), np.hypot(20.0, north))
    hold = _between(track, 10.0, 16.0)
    vel = np.where(hold[:, None], track.vel_mps[100], track.vel_mps)
    honest = _fly_fixed_at(
        track, _ins_reporting(track, vel, np.where(hold, 10.0 / 3.0 * (t - 10.0), 0.0)), set()
    )[1]
    blind = _fly_fixed_at(track, _ins_reporting(track, vel), set())[1]
    assert _beyond_3_sigma(track, honest) == []
    assert _beyond_3_sigma(track, blind) != []  # the same hold, unsaid, claims too little


def _wandering_hover(
    walk: float, seed: int = 3, correlation_s: float = 0.0, fix_bias_m: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """A hover whose 'INS' is an autopilot's estimate: its velocity wanders (Gauss-Markov, 1 m/s,
    10 s) and its position follows; fixes every 0.5 s, each off by 2 m of noise plus, where
    ``fix_bias_m``, an error they share that wanders slowly (Gauss-Markov, 30 s), claimed at the
    size of both. The filter's error and claimed sigma over the last 100 of 120 s."""
    rng = np.random.default_rng(seed)
    dt = 0.1
    keep, keep_bias = math.exp(-dt / 10.0), math.exp(-dt / 30.0)
    nav = NavFilter(
        FilterConfig.for_imu(CONSUMER, velocity_walk_mps_per_sqrt_s=walk, fix_correlation_s=correlation_s)
    )
    vel, pos, bias = np.zeros(2), np.zeros(2), rng.normal(0.0, fix_bias_m, 2)
    claimed_m2 = 16.0 + fix_bias_m**2
    errors, sigmas = [], []
    for k in range(1200):
        vel = vel * keep + rng.normal(0.0, math.sqrt(1.0 - keep**2), 2)
        bias = bias * keep_bias + rng.normal(0.0, fix_bias_m * math.sqrt(1.0 - keep_bias**2), 2)
        pos = pos + vel * dt
        lat, lon = (float(v) for v in FRAME.to_latlon(*pos))
        nav.predict(InsSample(k * dt, lat, lon, float(vel[0]), float(vel[1]), 0.0, 300.0))
        if k == 0:
            nav.initialise(0.0, LAT0, LON0, sigma_m=2.0, heading_sigma_deg=1.0)
        if k % 5 == 4:
            flat, flon = (float(v) for v in FRAME.to_latlon(*(bias + rng.normal(0.0, 2.0, 2))))
            fix = Fix(
                True,
                pose=Pose(flat, flon, 300.0, 0.0, 0.0, 0.0, flat, flon),
                covariance_enu_m2=np.eye(2) * claimed_m2,
            )
            nav.update(fix, k * dt)
        state = nav.state()
        if k >= 200:
            errors.append(float(np.hypot(*FRAME.to_enu(state.lat, state.lon))))
            sigmas.append(state.sigma_m)
    return np.array(errors), np.array(sigmas)


def test_an_autopilot_velocity_that_wanders_is_covered_by_the_velocity_walk() -> None:
    """The companion's case once GNSS is gone: with the velocity walk the claimed 3 sigma covers
    the error nearly always; modelled as an IMU alone the filter claims far less than it is off."""
    errors, sigmas = _wandering_hover(walk=0.5)
    assert np.mean(errors > 3.0 * sigmas) <= 0.02 and np.median(errors) < 3.0
    errors, sigmas = _wandering_hover(walk=0.0)
    assert np.mean(errors > 3.0 * sigmas) >= 0.2


def test_fixes_that_share_their_error_are_not_averaged_into_a_smaller_one() -> None:
    """Frames of the same ground share the map's error: ten fixes 5 m off together are one fix
    5 m off. Known no better than one of them, the claimed 3 sigma covers the error and the
    estimate is no further off; taken as independent, the filter claims a fraction of what it
    is off (over four flights)."""
    seeds = range(3, 7)
    shared = [_wandering_hover(0.5, seed, correlation_s=10.0, fix_bias_m=5.0) for seed in seeds]
    errors, sigmas = (np.concatenate(parts) for parts in zip(*shared, strict=True))
    assert np.mean(errors > 3.0 * sigmas) <= 0.02
    assert np.median(sigmas) <= 3.0 * np.percentile(errors, 95)  # cautious, not blind
    independent = [_wandering_hover(0.5, seed, fix_bias_m=5.0) for seed in seeds]
    blind_errors, blind_sigmas = (np.concatenate(parts) for parts in zip(*independent, strict=True))
    assert np.mean(blind_errors > 3.0 * blind_sigmas) >= 0.1
    assert np.median(errors) <= 1.2 * np.median(blind_errors)  # it follows the fixes as fast


@given(
    st.floats(0.5, 50.0),
    st.floats(0.5, 50.0),
    st.floats(0.0, 180.0),
)
def test_the_sigma_of_a_tilted_ellipse_is_its_long_axis(
    major_m: float, minor_m: float, angle_deg: float
) -> None:
    """One sigma must hold in every direction: the longest axis however the ellipse is turned,
    never the spread along north or east alone."""
    turn = np.radians(angle_deg)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    covariance = rotation @ np.diag([major_m**2, minor_m**2]) @ rotation.T
    sigma = worst_sigma(covariance)
    assert sigma == pytest.approx(max(major_m, minor_m), rel=1e-9)
    assert sigma >= math.sqrt(max(covariance[0, 0], covariance[1, 1])) - 1e-9


def test_a_zero_covariance_rounded_below_zero_has_a_zero_sigma() -> None:
    assert worst_sigma(np.diag([-1e-18, -1e-20])) == 0.0


def test_positive_definite_takes_a_rounded_covariance_and_refuses_a_flat_or_inverted_one() -> None:
    """Every check of a measurement's covariance (velocity, fix, SLAM odometry) asks this one
    question: a tilted ellipse with rounding asymmetry passes; a degenerate ellipse (a line) or
    one with a negative axis is refused, as one whose off-diagonal exceeds its diagonals."""
    turn = np.radians(30.0)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    tilted = rotation @ np.diag([25.0, 4.0]) @ rotation.T + np.array([[0.0, 1e-12], [0.0, 0.0]])
    assert positive_definite(tilted)
    assert positive_definite(np.diag([1.0, 2.0, 3.0]))
    assert not positive_definite(np.diag([25.0, 0.0]))
    assert not positive_definite(np.diag([4.0, -1e-9]))
    assert not positive_definite(np.array([[1.0, 2.0], [2.0, 1.0]]))
