"""The ground velocity between frames of a level camera (orthonav.fusion.ground_velocity) and its
fusion into the navigation filter: recovered within its claimed covariance on rendered frames,
refused where the frames cannot tell it; a biased INS velocity corrected by it, an outlier gated."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from orthonav.camera import Camera
from orthonav.frames.render import TruePose, render_frame
from orthonav.fusion import InsSample, NavFilter
from orthonav.fusion.ground_velocity import FrameVelocity, GroundVelocity, VelocityError
from orthonav.geo import GeoRaster, destination

ALT_M = 300.0
DT_S = 0.5


def _frames(raster: GeoRaster, camera: Camera, heading: float, course: float, speed: float):
    lat, lon = raster.center_latlon
    lat1, lon1 = destination(lat, lon, course, speed * DT_S)
    return (
        render_frame(raster, camera, TruePose(lat, lon, ALT_M, heading)),
        render_frame(raster, camera, TruePose(lat1, lon1, ALT_M, heading + 3.0)),
    )


@pytest.mark.parametrize(
    ("heading", "course", "speed"), [(0.0, 0.0, 10.0), (75.0, 200.0, 14.0), (300.0, 300.0, 4.0)]
)
def test_velocity_is_recovered_within_its_covariance(terrain_raster, camera, heading, course, speed):
    first, second = _frames(terrain_raster, camera, heading, course, speed)
    velocity = FrameVelocity(camera)
    assert velocity.add(first, 100.0, ALT_M, heading) is None  # a pair needs two frames
    measured = velocity.add(second, 100.0 + DT_S, ALT_M, heading + 3.0)
    truth = speed * np.array([math.sin(math.radians(course)), math.cos(math.radians(course))])
    error = np.array([measured.east_mps, measured.north_mps]) - truth
    distance = math.sqrt(error @ np.linalg.solve(measured.covariance_m2ps2, error))
    assert distance < 3.0, (error, measured.covariance_m2ps2)
    assert np.linalg.norm(error) < 0.1 * speed + 0.5
    assert measured.time_s == pytest.approx(100.0 + DT_S / 2) and measured.inliers >= 100


def test_frames_that_cannot_tell_a_velocity_are_refused(terrain_raster, camera):
    first, _ = _frames(terrain_raster, camera, 0.0, 0.0, 10.0)
    velocity = FrameVelocity(camera)
    velocity.add(first, 0.0, ALT_M, 0.0)
    with pytest.raises(VelocityError, match=r"matches|inliers"):
        velocity.add(np.full_like(first, 128), DT_S, ALT_M, 0.0)  # a blank frame
    with pytest.raises(VelocityError, match="matches"):  # the blank frame was the previous one
        velocity.add(first, 1.0, ALT_M, 0.0)
    hover = velocity.add(first, 1.5, ALT_M, 0.0)
    assert math.hypot(hover.east_mps, hover.north_mps) < 0.2
    assert velocity.add(first, 4.0, ALT_M, 0.0) is None  # too long after the previous frame
    with pytest.raises(VelocityError, match="height above ground"):
        velocity.add(first, 4.5, math.nan, 0.0)
    with pytest.raises(VelocityError, match="uint8 frame"):
        velocity.add(first[:100], 5.0, ALT_M, 0.0)


def _filter(
    bias_east: float, bias_north: float, truth=(8.0, -3.0), heading_sigma_deg: float = 0.5
) -> tuple[NavFilter, np.ndarray]:
    """A filter whose INS velocity is the truth plus a bias, initialised at t=0 with its heading
    known to ``heading_sigma_deg`` (as the fixes' headings make it known in flight)."""
    nav = NavFilter()
    lat, lon = 47.0, -99.0
    for k in range(41):
        t = k * 0.25
        nav.predict(
            InsSample(t, lat, lon, truth[0] + bias_east, truth[1] + bias_north, 90.0, alt_agl_m=ALT_M)
        )
        if k == 0:
            nav.initialise(0.0, lat, lon, 5.0, heading_sigma_deg)
    return nav, np.array(truth)


def _measured(time_s: float, vel: np.ndarray, sigma: float) -> GroundVelocity:
    return GroundVelocity(time_s, float(vel[0]), float(vel[1]), np.eye(2) * sigma**2, 300, DT_S)


@pytest.mark.parametrize(("bias_east", "bias_north"), [(1.5, 0.0), (-1.0, 1.0), (0.0, -2.0)])
def test_a_biased_ins_velocity_is_corrected_by_measured_velocities(bias_east, bias_north):
    nav, truth = _filter(bias_east, bias_north)
    before = np.array([nav.state().vel_east_mps, nav.state().vel_north_mps]) - truth
    rng = np.random.default_rng(7)
    for k in range(1, 21):
        outcome = nav.update_velocity(_measured(k * 0.5, truth + rng.normal(0.0, 0.3, 2), 0.3))
        assert outcome.accepted, outcome.reason
    state = nav.state()
    after = np.array([state.vel_east_mps, state.vel_north_mps]) - truth
    assert np.linalg.norm(after) < 0.35 * np.linalg.norm(before)
    assert state.velocity_sigma_mps < 0.5 and state.since_velocity_s == pytest.approx(0.0)


def test_a_velocity_turned_with_an_unknown_heading_leaves_the_velocity_across_it_unknown():
    """The camera's velocity is turned to east/north with the INS heading: with that heading
    uncertain, the velocity across the motion is as uncertain, however many are measured."""
    known, truth = _filter(0.0, 0.0, heading_sigma_deg=0.5)
    unknown, _ = _filter(0.0, 0.0, heading_sigma_deg=10.0)
    for k in range(1, 21):
        for nav in (known, unknown):
            assert nav.update_velocity(_measured(k * 0.5, truth, 0.2)).accepted
    across = np.array([truth[1], -truth[0]]) / np.linalg.norm(truth)
    sigma = [
        math.sqrt(across @ nav.state().velocity_covariance_enu_m2ps2 @ across) for nav in (known, unknown)
    ]
    speed = float(np.linalg.norm(truth))
    assert sigma[0] < 0.3 and sigma[1] > 0.5 * speed * math.radians(10.0)


def test_an_outlier_velocity_is_gated_out_and_changes_nothing():
    nav, truth = _filter(0.0, 0.0)
    for k in range(1, 11):
        assert nav.update_velocity(_measured(k * 0.5, truth, 0.3)).accepted
    state = nav.state()
    outcome = nav.update_velocity(_measured(9.0, truth + np.array([6.0, -4.0]), 0.3))
    assert not outcome.accepted and outcome.reason.startswith("mahalanobis")
    after = nav.state()
    assert (after.vel_east_mps, after.vel_north_mps, after.lat) == (
        state.vel_east_mps,
        state.vel_north_mps,
        state.lat,
    )


def test_no_velocity_is_fused_into_a_filter_that_does_not_know_where_it_is():
    nav = NavFilter()
    nav.predict(InsSample(0.0, 47.0, -99.0, 5.0, 0.0, 90.0, alt_agl_m=ALT_M))
    nav.predict(InsSample(1.0, 47.0, -99.0, 5.0, 0.0, 90.0, alt_agl_m=ALT_M))
    outcome = nav.update_velocity(_measured(0.5, np.array([5.0, 0.0]), 0.3))
    assert not outcome.accepted and "uninitialised" in outcome.reason
    bad = GroundVelocity(0.5, 5.0, 0.0, np.array([[0.1, 0.0], [0.0, -0.1]]), 300, DT_S)
    assert "positive definite" in nav.update_velocity(bad).reason


def test_the_offline_grade_of_a_kept_flight_matches_its_truth(terrain_raster, camera, tmp_path):
    """bench.frame_velocity on a flight folder as bench sitl leaves it: frames named by capture
    time, the truth track, the companion's telemetry; a straight 10 m/s flight east."""
    from orthonav.bench.frame_velocity import measure
    from orthonav.frames import frame_filename

    lat0, lon0 = terrain_raster.center_latlon
    (tmp_path / "camera").mkdir()
    (tmp_path / "fly").mkdir()
    truth, lines = [], []
    for k in range(12):
        t = 1000.0 + k * DT_S
        lat, lon = destination(lat0, lon0, 90.0, 10.0 * k * DT_S - 30.0)
        truth.append((t, lat, lon))
        image = render_frame(terrain_raster, camera, TruePose(lat, lon, ALT_M, 90.0))
        cv2.imwrite(str(tmp_path / "camera" / frame_filename(t)), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        for kind, msg in (
            ("ATTITUDE", {"yaw": math.radians(90.0)}),
            ("GLOBAL_POSITION_INT", {"relative_alt": ALT_M * 1e3, "vx": 0.0, "vy": 1000.0}),
        ):
            lines.append(json.dumps({"kind": "recv", "time_s": t, "type": kind, "msg": msg}))
    track = {"home": [lat0, lon0], "gnss_off_at": 1001.0, "truth": truth, "reached": [[1003.0, 2]]}
    (tmp_path / "track.json").write_text(json.dumps(track))
    (tmp_path / "fly" / "companion.jsonl").write_text("\n".join(lines) + "\n")
    result = measure(tmp_path, camera.hfov_deg)
    graded = result["all"]
    assert result["frames"] == 12 and graded["n"] == 11
    assert graded["error_p95_mps"] < 0.5 and graded["within_1_2_3_sigma"][2] == 1.0
    assert graded["autopilot_error_p95_mps"] < 0.1  # the telemetry said the truth
    assert [part["n"] for part in result["parts"]] == [2, 4, 5]
    assert [(band["from_m"], band["n"], band["refused"]) for band in result["heights"]] == [(300.0, 11, 0)]
    demanding = measure(tmp_path, camera.hfov_deg, min_inliers=100_000)  # no pair has as many
    assert demanding["min_inliers"] == 100_000 and demanding["velocities"] == 0
    assert demanding["heights"] == [{"from_m": 300.0, "refused": 11, "n": 0}]


@pytest.mark.parametrize("step_deg", [4.0, -5.0])
def test_a_step_of_the_autopilots_heading_is_learnt_from_the_fixes_within_seconds(step_deg):
    """With the heading walk frame velocities need, the fixes' headings (2 deg each, five a second)
    tell the filter of a step in the INS heading within seconds; without it, an IMU's drift rate
    would take many times longer, and the velocities turned with the INS heading carry the step."""
    from orthonav.fusion import FilterConfig
    from orthonav.fusion.ground_velocity import HEADING_WALK_DEG_PER_SQRT_S
    from orthonav.types import Fix, Pose

    learnt = {}
    for walk in (HEADING_WALK_DEG_PER_SQRT_S, 0.0):
        nav = NavFilter(FilterConfig(heading_walk_deg_per_sqrt_s=walk))
        rng = np.random.default_rng(3)
        for k in range(101):  # 20 s at 5 Hz; the INS heading steps at 5 s
            t = k * 0.2
            heading = 90.0 + (step_deg if t >= 5.0 else 0.0)
            nav.predict(InsSample(t, 47.0, -99.0, 0.0, 0.0, heading, alt_agl_m=ALT_M))
            if k == 0:
                nav.initialise(0.0, 47.0, -99.0, 5.0, 1.0)
            pose = Pose(47.0, -99.0, ALT_M, 90.0 + rng.normal(0.0, 1.0), 0.0, 0.0, 47.0, -99.0)
            nav.update(Fix(True, pose=pose, covariance_enu_m2=np.eye(2) * 25.0, method="test"), t)
            if t == pytest.approx(10.0):
                learnt[walk] = nav.state().heading_deg - 90.0
    # Five seconds after the step the estimate is back within a quarter of it, and far nearer the
    # truth than without the walk.
    assert abs(learnt[HEADING_WALK_DEG_PER_SQRT_S]) < 0.25 * abs(step_deg)
    assert abs(learnt[0.0]) > 2.0 * abs(learnt[HEADING_WALK_DEG_PER_SQRT_S])
