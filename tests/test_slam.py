"""SLAM parts on synthetic geometry: rig validation, metrics, two-UAV stereo, the gtsam graph."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from orthonav.camera import Camera, CameraPose, pixel_to_ground, project_ground
from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet
from orthonav.slam import Rig, RigCamera, ate_m, landmark_errors_m, rpe_m, stereo
from orthonav.slam.association import Tracks, View, overlap_fraction
from orthonav.slam.spotting import project_points

CAM = Camera.from_hfov(640, 480, 60.0)


def _rig_dict(**overrides) -> dict:
    nadir = {"name": "nadir", "width": 640, "height": 480, "hfov_deg": 60}
    oblique = {**nadir, "name": "forward", "pitch_deg": 25}
    return {"cameras": [nadir, {**oblique, **overrides}]}


# --- rig -----------------------------------------------------------------------------------


def test_rig_mount_angles_turn_the_camera_as_documented() -> None:
    nadir = RigCamera.from_angles("n", CAM)
    forward = RigCamera.from_angles("f", CAM, pitch_deg=25.0)
    left = RigCamera.from_angles("l", CAM, roll_deg=20.0)
    assert np.allclose(nadir.camera_attitude_deg(30.0, 0.0, 0.0), (30.0, 0.0, 0.0), atol=1e-9)
    assert np.allclose(forward.camera_attitude_deg(30.0, 0.0, 0.0), (30.0, 25.0, 0.0), atol=1e-9)
    assert forward.tilt_deg == pytest.approx(25.0)
    # Optical axis (camera z) in the body frame: forward camera leans to +x, left camera to -y (left).
    assert forward.body_r_camera[0, 2] > 0.4 and left.body_r_camera[1, 2] < -0.3
    # The frame centre of the forward camera lies ahead of the vehicle by alt * tan(25 deg).
    pose = forward.camera_pose(0.0, 0.0, 1000.0, 90.0)
    centre = pixel_to_ground(CAM, pose, np.array([[CAM.cx, CAM.cy]]))[0]
    assert centre == pytest.approx([1000.0 * math.tan(math.radians(25.0)), 0.0], abs=1e-6)


def test_rig_from_json_with_a_rotation_matrix(tmp_path) -> None:
    matrix = RigCamera.from_angles("x", CAM, pitch_deg=25.0).body_r_camera.tolist()
    data = _rig_dict(rotation=matrix)
    del data["cameras"][1]["pitch_deg"]
    path = tmp_path / "rig.json"
    path.write_text(__import__("json").dumps(data))
    rig = Rig.from_json(path)
    assert rig.names == ["nadir", "forward"]
    assert rig.cameras[1].tilt_deg == pytest.approx(25.0)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"rotation": [[1, 0, 0], [0, 1, 0], [0, 0.2, 1]]}, "not orthonormal"),
        ({"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, -1]]}, "reflection"),
        ({"rotation": [[1, 0], [0, 1]]}, "3x3"),
        ({"name": "nadir"}, "duplicate camera name"),
        ({"pitch_deg": 75}, "above the horizon"),
        ({"roll_deg": -80}, "above the horizon"),
        ({"lever_arm_m": [0, 0, 50]}, "lever_arm_m"),
        ({"lever_arm_m": "here"}, "lever_arm_m"),
        ({"hfov_deg": 400}, "hfov_deg"),
    ],
)
def test_inconsistent_rigs_are_refused_naming_the_camera(overrides: dict, message: str) -> None:
    with pytest.raises(OrthonavError, match=message):
        Rig.from_dict(_rig_dict(**overrides))


def test_empty_or_malformed_rig_is_refused() -> None:
    with pytest.raises(OrthonavError, match="at least one camera"):
        Rig.from_dict({"cameras": []})
    with pytest.raises(OrthonavError, match="'name'"):
        Rig.from_dict({"cameras": [{"width": 640, "height": 480, "hfov_deg": 60}]})
    with pytest.raises(OrthonavError, match="no camera named"):
        Rig.from_dict(_rig_dict()).subset(["rear"])


# --- metrics ---------------------------------------------------------------------------------


def _circle(n: int = 20, yaw_offset_deg: float = 0.0, shift: float = 0.0) -> np.ndarray:
    theta = np.linspace(0, 1.5, n)
    east, north = 900 * np.cos(theta), 900 * np.sin(theta)
    track = np.column_stack([east, north, np.full(n, 1000.0), np.degrees(-theta) % 360])
    a = math.radians(yaw_offset_deg)  # rotate the whole track about its start
    rel = track[:, :2] - track[0, :2]
    track[:, 0] = track[0, 0] + rel[:, 0] * math.cos(a) + rel[:, 1] * math.sin(a)
    track[:, 1] = track[0, 1] - rel[:, 0] * math.sin(a) + rel[:, 1] * math.cos(a)
    track[:, 3] += yaw_offset_deg
    track[:, 0] += shift
    return track


def test_ate_and_rpe() -> None:
    truth = _circle()
    assert ate_m(_circle(shift=3.0), truth) == pytest.approx(3.0)
    assert rpe_m(_circle(shift=3.0), truth) == pytest.approx(0.0, abs=1e-9)
    rotated = _circle(yaw_offset_deg=2.0)
    assert ate_m(rotated, truth) > 20.0  # a heading offset grows into position error...
    assert rpe_m(rotated, truth) == pytest.approx(0.0, abs=1e-6)  # ...but not into the local steps
    assert landmark_errors_m(np.zeros((2, 3)), np.array([[3.0, 4.0, 0.0], [0, 0, 1.0]])) == pytest.approx(
        [5, 1]
    )
    with pytest.raises(OrthonavError, match="one shape"):
        ate_m(truth[:5], truth)
    with pytest.raises(OrthonavError, match="delta"):
        rpe_m(truth[:1], truth[:1])


# --- two-UAV stereo ------------------------------------------------------------------------


def _two_uavs(offset_m: float) -> tuple[RigCamera, CameraPose, CameraPose, np.ndarray]:
    """UAV 1 at 1000 m heading north, UAV 2 ``offset_m`` to its left at 800 m, both nadir."""
    spotter = RigCamera.from_angles(
        "spot",
        Camera.from_hfov(640, 480, 10.0),
        yaw_deg=-90.0,
        pitch_deg=math.degrees(math.atan2(offset_m, 200.0)),
    )
    pose_a = CameraPose(0.0, 0.0, 1000.0, 0.0)
    pose_b = CameraPose(-offset_m, 0.0, 800.0, 0.0)
    return spotter, pose_a, pose_b, np.array([-offset_m, 0.0, 800.0])


def test_baseline_from_the_other_uavs_known_size() -> None:
    spotter, _, _, other = _two_uavs(300.0)
    pose = spotter.camera_pose(0.0, 0.0, 1000.0, 0.0)
    (centre,), (depth,) = project_points(spotter.camera, pose, other[None])
    sighting = stereo.Sighting(tuple(centre), math.sqrt(spotter.camera.fx * spotter.camera.fy) * 4.0 / depth)
    assert sighting.span_px > 10
    baseline = stereo.baseline_from_sighting(spotter, sighting, 4.0)
    # Body FRD at heading north: the other UAV is 300 m to the left (-right) and 200 m below (+down).
    assert baseline.vector_body_m == pytest.approx([0.0, -300.0, 200.0], abs=1e-6)
    assert 0 < baseline.range_sigma_m < 0.1 * baseline.range_m
    with pytest.raises(OrthonavError, match="outside"):
        stereo.baseline_from_sighting(spotter, stereo.Sighting((900.0, 10.0), 20.0), 4.0)
    with pytest.raises(OrthonavError, match="at least 2 px"):
        stereo.baseline_from_sighting(spotter, stereo.Sighting((300.0, 200.0), 1.0), 4.0)


def _pair(offset_m: float, baseline_error: float = 0.0) -> tuple[stereo.StereoPair, np.ndarray]:
    _, pose_a, pose_b, _ = _two_uavs(offset_m)
    ground = np.random.default_rng(0).uniform(-250, 100, (30, 2))
    from orthonav.camera import rotation_enu_from_camera

    baseline = np.array([-offset_m, 0.0, -200.0]) * (1 + baseline_error)
    pair = stereo.StereoPair(
        CAM,
        CAM,
        rotation_enu_from_camera(0, 0, 0),
        rotation_enu_from_camera(0, 0, 0),
        baseline,
        0.005 * float(baseline @ baseline) / 300.0,  # sigma_B grows as B^2
        project_ground(CAM, pose_a, ground),
        project_ground(CAM, pose_b, ground),
    )
    true = np.column_stack([ground, np.zeros(len(ground))]) - [0.0, 0.0, 1000.0]
    return pair, true


def test_stereo_distance_and_size_with_the_measured_baseline() -> None:
    pair, true = _pair(300.0)
    points = stereo.triangulate(pair)
    assert points == pytest.approx(true, abs=1e-6)
    index = np.array([[0, 1], [2, 3]])
    assert stereo.sizes_m(points, index) == pytest.approx(stereo.sizes_m(true, index))
    # A 10 % wrong baseline scales every distance by 10 %.
    wrong, _ = _pair(300.0, baseline_error=0.1)
    ratio = np.linalg.norm(stereo.triangulate(wrong), axis=1) / np.linalg.norm(true, axis=1)
    assert ratio == pytest.approx(1.1, rel=1e-6)


def test_best_pair_weighs_baseline_length_against_its_error() -> None:
    pairs = [_pair(offset)[0] for offset in (60.0, 300.0, 2000.0)]
    index, points, predicted = stereo.best_pair(pairs)
    assert index == 1 and len(points) == 30 and predicted > 0
    with pytest.raises(OrthonavError, match="no frame pair"):
        stereo.best_pair([])


def test_stereo_refuses_frames_sharing_half_their_ground_or_less() -> None:
    _, pose_a, _, _ = _two_uavs(300.0)
    assert stereo.check_overlap(CAM, pose_a, CAM, CameraPose(-300.0, 0.0, 800.0, 0.0)) > 0.5
    with pytest.raises(OrthonavError, match="more than 50 %"):
        stereo.check_overlap(CAM, pose_a, CAM, CameraPose(-900.0, 0.0, 1000.0, 0.0))


# --- association -----------------------------------------------------------------------------


def _view(uav: int, keyframe: int, n: int = 3) -> View:
    feats = FeatureSet(np.zeros((n, 2), np.float32), np.zeros((n, 32), np.uint8), np.zeros(n, np.float32))
    return View(uav, keyframe, 0, feats, np.zeros((n, 2)), np.zeros((4, 2)))


def test_tracks_join_matches_and_never_take_two_keypoints_of_one_view() -> None:
    views = [_view(0, 0), _view(0, 1), _view(1, 1)]
    tracks = Tracks()
    t = tracks.link(views, (1, 0), (0, 0))
    assert tracks.link(views, (2, 0), (0, 0)) == t  # the other UAV joins the same ground point
    assert tracks.places(views, t) == {(0, 0), (0, 1), (1, 1)}
    assert tracks.link(views, (1, 1), (0, 0)) is None  # view 1 already has a keypoint in it
    u = tracks.link(views, (1, 2), (0, 2))
    tracks.in_graph.update({t, u})
    assert tracks.link(views, (2, 2), (0, 2)) == u
    assert overlap_fraction(
        np.array([[0, 0], [2, 0], [2, 2], [0, 2]]), np.array([[1, 0], [3, 0], [3, 2], [1, 2]])
    ) == (pytest.approx(0.5))


# --- graph (gtsam) --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Motion:
    right_m: float
    forward_m: float
    dyaw_deg: float
    covariance: np.ndarray


def test_graph_recovers_poses_from_exact_odometry_and_landmarks() -> None:
    pytest.importorskip("gtsam", reason="the 'slam' extra (gtsam) is not installed")
    from orthonav.slam.graph import SlamGraph, body_pose, yaw_deg_of

    rig = Rig((RigCamera.from_angles("nadir", CAM), RigCamera.from_angles("forward", CAM, pitch_deg=25.0)))
    truth = _circle(8)
    graph = SlamGraph([rig])
    rng = np.random.default_rng(1)
    ground = rng.uniform(-200, 1100, (400, 2))
    cov = np.diag([0.3, 0.3, 0.01]) ** 2
    for k, (e, n, alt, yaw) in enumerate(truth):
        if k == 0:
            graph.add_pose(0, 0, body_pose(e, n, alt, yaw))
            graph.add_start_prior(0, 0, body_pose(e, n, alt, yaw))
        else:
            d = truth[k, :2] - truth[k - 1, :2]
            psi = math.radians(truth[k - 1, 3])
            motion = _Motion(
                d @ [math.cos(psi), -math.sin(psi)],
                d @ [math.sin(psi), math.cos(psi)],
                (yaw - truth[k - 1, 3] + 180) % 360 - 180,
                cov,
            )
            graph.add_pose(0, k, body_pose(e + 20.0, n - 15.0, alt, yaw + 1.0))  # a poor initial guess
            graph.add_odometry(0, k - 1, k, motion)
        graph.add_attitude(0, k, 0.0, 0.0)
        graph.add_altitude(0, k, alt)
        for c, cam in enumerate(rig.cameras):
            pose = cam.camera_pose(e, n, alt, yaw)
            px = project_ground(CAM, pose, ground)
            seen = np.flatnonzero((px[:, 0] > 0) & (px[:, 0] < 640) & (px[:, 1] > 0) & (px[:, 1] < 480))
            for i in seen:
                if i not in graph.landmarks:
                    graph.add_landmark(int(i), np.array([*ground[i] + 5.0, 0.0]))
                graph.add_observation(0, k, c, int(i), px[i])
        graph.update()
    for k, (e, n, alt, yaw) in enumerate(truth):
        pose = graph.pose(0, k)
        assert pose.translation() == pytest.approx([e, n, alt], abs=0.5)
        assert (yaw_deg_of(pose) - yaw + 180) % 360 - 180 == pytest.approx(0.0, abs=0.05)
    some = sorted(graph.landmarks)[:20]
    assert np.max([np.linalg.norm(graph.landmark(i)[:2] - ground[i]) for i in some]) < 0.5
    assert 5.0 < graph.position_sigma_m(0, 7) < 40.0  # held by the launch compass (1 deg) alone


def test_graph_refuses_unusable_odometry_and_places_a_uav_by_its_baseline() -> None:
    pytest.importorskip("gtsam", reason="the 'slam' extra (gtsam) is not installed")
    from orthonav.slam.graph import GraphConfig, SlamGraph, body_pose

    rig = Rig((RigCamera.from_angles("nadir", CAM),))
    graph = SlamGraph([rig, rig], GraphConfig(start_sigma_m=300.0))  # launch points poorly known
    start = body_pose(0.0, 0.0, 1000.0, 0.0)
    graph.add_pose(0, 0, start)
    graph.add_start_prior(0, 0, start)
    graph.add_fix(0, 0, 0.0, 0.0, np.eye(2), 1000.0)  # UAV 1 has a map fix
    graph.add_pose(0, 1, start)
    for bad, message in (
        (_Motion(0.0, float("nan"), 0.0, np.eye(3)), "finite"),
        (_Motion(0.0, 0.0, 0.0, np.zeros((3, 3))), "positive definite"),
        (_Motion(0.0, 0.0, 0.0, np.eye(2)), "3x3"),
    ):
        with pytest.raises(OrthonavError, match=message):
            graph.add_odometry(0, 0, 1, bad)
    # Degenerate motion (hovering) is a valid measurement: the pose stays put.
    graph.add_odometry(0, 0, 1, _Motion(0.0, 0.0, 0.0, np.diag([0.5, 0.5, 0.1]) ** 2))
    # UAV 2, 300 m to the left and 200 m below, known only through UAV 1's sighting of it.
    guess = body_pose(-250.0, 40.0, 800.0, 0.0)
    graph.add_pose(1, 0, guess)
    graph.add_start_prior(1, 0, guess)
    graph.add_attitude(1, 0, 0.0, 0.0)
    graph.add_altitude(1, 0, 800.0)
    vector = np.array([0.0, -300.0, 200.0])
    graph.add_baseline(0, 1, 0, vector / np.linalg.norm(vector), float(np.linalg.norm(vector)), 1e-3, 2.0)
    graph.update()
    assert graph.pose(0, 1).translation() == pytest.approx([0.0, 0.0, 1000.0], abs=1.0)
    assert graph.pose(1, 0).translation() == pytest.approx([-300.0, 0.0, 800.0], abs=2.0)


def test_best_pair_counts_only_the_baseline_across_the_line_of_sight() -> None:
    """Two pairs with baselines of one length: the one mostly along the nadir view has little parallax."""
    pair, _ = _pair(300.0)
    along = stereo.StereoPair(
        *[getattr(pair, f) for f in ("camera_a", "camera_b", "r_enu_cam_a", "r_enu_cam_b")],
        np.array([-100.0, 0.0, -float(np.sqrt(300.0**2 + 200.0**2 - 100.0**2))]),
        pair.baseline_sigma_m,
        pair.pixels_a,
        pair.pixels_b,
    )
    assert stereo.predicted_distance_error_m(1000.0, along) > stereo.predicted_distance_error_m(1000.0, pair)


# --- the other UAV drawn into a frame and detected ---------------------------------------------

SPOTTER_CAM = Camera.from_hfov(640, 480, 10.0)


def _spotter_frame(depth_m: float, east_m: float = 0.0, photometric: float = 1.0, seed: int = 0):
    """A textured ground seen by a 10 deg camera looking straight down, the UAV ``depth_m`` below it."""
    import cv2

    from orthonav.frames import Photometric
    from orthonav.slam.spotting import composite_uav

    rng = np.random.default_rng(seed)
    ground = cv2.GaussianBlur(rng.integers(40, 200, (480, 640, 3), dtype=np.uint8), (0, 0), 2.0)
    pose = CameraPose(0.0, 0.0, 1000.0, 0.0)
    frame = composite_uav(ground, SPOTTER_CAM, pose, np.array([east_m, 0.0, 1000.0 - depth_m]), 33.0, 4.0)
    return Photometric.random(rng, photometric).apply(frame, rng), ground


@pytest.mark.parametrize("depth_m", [150.0, 400.0, 900.0])
def test_the_other_uav_is_detected_with_its_centre_and_span(depth_m: float) -> None:
    from orthonav.slam.spotting import detect_uav

    frame, ground = _spotter_frame(depth_m)
    detection = detect_uav(frame)
    true_span = SPOTTER_CAM.fx * 4.0 / depth_m
    assert detection.found, detection.reason
    assert detection.sighting.centre_px == pytest.approx((320.0, 240.0), abs=0.5)
    assert detection.sighting.span_px == pytest.approx(true_span, abs=1.5)  # blur and noise: ~1 px
    assert not detect_uav(ground).found  # no false detection on the bare ground
    gated = detect_uav(frame, expected_span_px=3 * true_span)
    assert not gated.found and "expected" in gated.reason


def test_an_out_of_view_too_small_or_cut_uav_is_refused_with_the_reason() -> None:
    from orthonav.slam.spotting import detect_uav

    out_of_view = detect_uav(_spotter_frame(400.0, east_m=60.0)[0])  # 60 m aside at 400 m: off the frame
    assert not out_of_view.found and "no ring-coloured pixels" in out_of_view.reason
    too_small = detect_uav(_spotter_frame(3000.0, photometric=0.2)[0])  # about 5 px
    assert not too_small.found and "too small" in too_small.reason
    cut = detect_uav(_spotter_frame(400.0, east_m=34.0, photometric=0.2)[0])  # across the right edge
    assert not cut.found and "frame edge" in cut.reason
