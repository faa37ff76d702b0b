"""Camera model: intrinsics, footprint, ground<->image homographies, pose recovery, JSON, distortion."""

from __future__ import annotations

import codecs
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from orthonav.camera import (
    AttitudePrior,
    Camera,
    CameraPose,
    apply_homography,
    footprint_enu,
    ground_to_image_homography,
    pose_from_homography,
    project_ground,
    project_points,
    refine_pose,
)
from orthonav.camera.model import DISTORTION_KEYS
from orthonav.errors import OrthonavError

CAM = Camera.from_hfov(640, 480, 60.0)


def angle_diff(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


# --- intrinsics --------------------------------------------------------------------------------


@pytest.mark.parametrize(("width", "height", "hfov"), [(640, 480, 60.0), (4000, 2250, 84.0), (100, 100, 5.0)])
def test_from_hfov_focal_length(width: int, height: int, hfov: float) -> None:
    """f = (W/2) / tan(hfov/2), square pixels, principal point at the centre, hfov round-trips."""
    cam = Camera.from_hfov(width, height, hfov)
    f = (width / 2) / math.tan(math.radians(hfov) / 2)
    assert cam.fx == pytest.approx(f) and cam.fy == pytest.approx(f)
    assert (cam.cx, cam.cy) == (width / 2, height / 2)
    assert cam.hfov_deg == pytest.approx(hfov)
    np.testing.assert_allclose(cam.K, [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]])


@pytest.mark.parametrize("alt", [20.0, 150.0, 3000.0])
def test_nadir_footprint_closed_form(alt: float) -> None:
    """Footprint = 2 h tan(fov/2) in both axes, from nadir_footprint_m and from footprint_enu."""
    hfov = math.radians(60.0)
    vfov = 2 * math.atan(math.tan(hfov / 2) * 480 / 640)  # square pixels, centred principal point
    width_m, height_m = 2 * alt * math.tan(hfov / 2), 2 * alt * math.tan(vfov / 2)
    assert CAM.nadir_footprint_m(alt) == pytest.approx((width_m, height_m))
    corners = footprint_enu(CAM, CameraPose(0.0, 0.0, alt, 0.0))
    assert corners[:, 0].max() - corners[:, 0].min() == pytest.approx(width_m)
    assert corners[:, 1].max() - corners[:, 1].min() == pytest.approx(height_m)
    assert CAM.nadir_gsd_m(alt) == pytest.approx(width_m / 640)


@pytest.mark.parametrize("heading", [0.0, 30.0, 90.0, 135.0, 180.0, 270.0, 333.0])
def test_footprint_is_rotated_rectangle_with_top_towards_heading(heading: float) -> None:
    """Nadir footprint: the W x H rectangle around the camera, image top along the heading."""
    e0, n0, alt = 120.0, -40.0, 200.0
    corners = footprint_enu(CAM, CameraPose(e0, n0, alt, heading))
    w, h = CAM.nadir_footprint_m(alt)
    # Image axes on the ground: right is heading + 90, up (image top) is heading.
    yaw = math.radians(heading)
    fwd = np.array([math.sin(yaw), math.cos(yaw)])
    right = np.array([math.cos(yaw), -math.sin(yaw)])
    centre = np.array([e0, n0])
    expected = np.array(
        [
            centre - right * w / 2 + fwd * h / 2,  # top-left
            centre + right * w / 2 + fwd * h / 2,  # top-right
            centre + right * w / 2 - fwd * h / 2,  # bottom-right
            centre - right * w / 2 - fwd * h / 2,  # bottom-left
        ]
    )
    np.testing.assert_allclose(corners, expected, atol=1e-6)
    top_mid = (corners[0] + corners[1]) / 2 - centre
    azimuth = math.degrees(math.atan2(top_mid[0], top_mid[1])) % 360.0
    assert angle_diff(azimuth, heading) < 1e-6


def test_footprint_refuses_horizon_in_view() -> None:
    """A 70 deg nose-up pitch with a 60 deg FOV sees the sky: OrthonavError, not nonsense corners."""
    with pytest.raises(OrthonavError, match="horizon"):
        footprint_enu(CAM, CameraPose(0.0, 0.0, 100.0, 0.0, pitch_deg=70.0))


# --- homographies ------------------------------------------------------------------------------


@pytest.mark.parametrize("yaw", [0.0, 45.0, 200.0])
def test_point_below_nadir_camera_projects_to_principal_point(yaw: float) -> None:
    """The ground point under a nadir camera maps to (cx, cy); a point d ahead maps f d / h up."""
    cam = Camera(640, 480, 500.0, 500.0, 300.0, 250.0)
    pose = CameraPose(35.0, -12.0, 120.0, yaw)
    h = ground_to_image_homography(cam, pose)
    ahead = np.array([35.0 + 10 * math.sin(math.radians(yaw)), -12.0 + 10 * math.cos(math.radians(yaw))])
    pts = np.array([[35.0, -12.0], ahead, [35.0, -12.0]])
    homog = np.column_stack([pts, np.ones(3)]) @ h.T
    px = homog[:, :2] / homog[:, 2:]
    np.testing.assert_allclose(px[0], [300.0, 250.0], atol=1e-9)
    np.testing.assert_allclose(px[1], [300.0, 250.0 - 500.0 * 10 / 120.0], atol=1e-9)
    np.testing.assert_allclose(project_ground(cam, pose, pts), px, atol=1e-9)


def test_apply_homography_of_the_inverse_inverts_projection() -> None:
    """Projecting ground points and mapping them back with the inverse homography returns them."""
    pose = CameraPose(5.0, 6.0, 300.0, 77.0, 8.0, -5.0)
    ground = np.random.default_rng(3).uniform(-50, 50, (20, 2))
    px = project_ground(CAM, pose, ground)
    back = apply_homography(np.linalg.inv(ground_to_image_homography(CAM, pose)), px)
    np.testing.assert_allclose(back, ground, atol=1e-8)


@settings(max_examples=80, deadline=None)
@given(
    east=st.floats(-2000.0, 2000.0),
    north=st.floats(-2000.0, 2000.0),
    alt=st.floats(20.0, 3000.0),
    yaw=st.floats(0.0, 359.99),
    pitch=st.floats(-15.0, 15.0),
    roll=st.floats(-15.0, 15.0),
)
def test_pose_from_homography_recovers_pose(
    east: float, north: float, alt: float, yaw: float, pitch: float, roll: float
) -> None:
    """Decomposing the image->ground homography of a pose gives that pose back."""
    pose = CameraPose(east, north, alt, yaw, pitch, roll)
    h_img_to_ground = np.linalg.inv(ground_to_image_homography(CAM, pose))
    got = pose_from_homography(CAM, h_img_to_ground)
    tol_m = 1e-6 * max(alt, abs(east), abs(north))
    assert got.east_m == pytest.approx(east, abs=tol_m)
    assert got.north_m == pytest.approx(north, abs=tol_m)
    assert got.alt_agl_m == pytest.approx(alt, abs=tol_m)
    assert angle_diff(got.yaw_deg, yaw) < 1e-6
    assert got.pitch_deg == pytest.approx(pitch, abs=1e-6)
    assert got.roll_deg == pytest.approx(roll, abs=1e-6)


def test_pose_from_homography_scale_invariant() -> None:
    """A homography is defined up to scale (sign included): any multiple decodes to the same pose."""
    pose = CameraPose(10.0, 20.0, 250.0, 123.0, 3.0, -2.0)
    h = np.linalg.inv(ground_to_image_homography(CAM, pose))
    for factor in (1e-3, -1.0, 42.0):
        got = pose_from_homography(CAM, h * factor)
        assert got.alt_agl_m == pytest.approx(250.0, rel=1e-9)
        assert angle_diff(got.yaw_deg, 123.0) < 1e-6


# --- pose refinement ---------------------------------------------------------------------------


def noisy_correspondences(
    pose: CameraPose, sigma_px: float, n: int = 200, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Ground points seen across the frame and their projections with Gaussian pixel noise."""
    rng = np.random.default_rng(seed)
    px = rng.uniform([0, 0], [CAM.width, CAM.height], (n, 2))
    ground = apply_homography(np.linalg.inv(ground_to_image_homography(CAM, pose)), px)
    return project_ground(CAM, pose, ground) + rng.normal(0.0, sigma_px, (n, 2)), ground


@pytest.mark.parametrize("fix_attitude", [True, False])
def test_refine_pose_recovers_pose_from_noisy_points(fix_attitude: bool) -> None:
    """From a 5 m / 10 m / 3 deg wrong start and 0.5 px noise, the pose comes back to a few cm."""
    true = CameraPose(12.0, -7.0, 150.0, 37.0, 4.0, -3.0)
    sigma = 0.5
    frame_px, ground = noisy_correspondences(true, sigma)
    start = CameraPose(
        17.0,
        -2.0,
        160.0,
        40.0,
        true.pitch_deg + (0 if fix_attitude else 2),
        true.roll_deg - (0 if fix_attitude else 2),
    )
    pose, cov, rms = refine_pose(CAM, frame_px, ground, start, fix_attitude=fix_attitude)
    # One pixel of noise is this many metres on the ground; averaging 200 points beats it.
    noise_m = sigma * CAM.nadir_gsd_m(true.alt_agl_m)
    assert math.hypot(pose.east_m - true.east_m, pose.north_m - true.north_m) < noise_m
    assert abs(pose.alt_agl_m - true.alt_agl_m) < noise_m
    assert angle_diff(pose.yaw_deg, true.yaw_deg) < 0.05
    if fix_attitude:
        assert (pose.pitch_deg, pose.roll_deg) == (true.pitch_deg, true.roll_deg)
    else:
        assert abs(pose.pitch_deg - true.pitch_deg) < 0.1 and abs(pose.roll_deg - true.roll_deg) < 0.1
    # Residual RMS is the per-point error norm: sqrt(2) sigma for isotropic noise.
    assert rms == pytest.approx(math.sqrt(2) * sigma, rel=0.15)
    n_params = 4 if fix_attitude else 6
    assert cov.shape == (n_params, n_params)
    np.testing.assert_allclose(cov, cov.T, rtol=1e-6, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    # The covariance is honest: the actual errors are within 4 sigma.
    errors = np.array(
        [
            pose.east_m - true.east_m,
            pose.north_m - true.north_m,
            pose.alt_agl_m - true.alt_agl_m,
            (pose.yaw_deg - true.yaw_deg + 180) % 360 - 180,
            pose.pitch_deg - true.pitch_deg,
            pose.roll_deg - true.roll_deg,
        ][:n_params]
    )
    assert np.all(np.abs(errors) < 4 * np.sqrt(np.diag(cov)))


def test_refine_pose_exact_data_converges_exactly() -> None:
    """Without noise the refinement lands on the true pose with ~zero residual."""
    true = CameraPose(-30.0, 45.0, 500.0, 300.0, -6.0, 9.0)
    frame_px, ground = noisy_correspondences(true, 0.0, n=50)
    start = CameraPose(-20.0, 40.0, 520.0, 303.0, -4.0, 7.0)
    pose, _, rms = refine_pose(CAM, frame_px, ground, start)
    assert rms < 1e-3
    assert math.hypot(pose.east_m - true.east_m, pose.north_m - true.north_m) < 1e-3
    assert angle_diff(pose.yaw_deg, true.yaw_deg) < 1e-4


def terrain_correspondences(
    pose: CameraPose, sigma_px: float, relief_m: float, n: int = 300, seed: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Points on hilly ground (ENU, up in the pose's datum) and their noisy projections."""
    rng = np.random.default_rng(seed)
    en = rng.uniform(-60, 60, (n, 2)) + np.array([pose.east_m, pose.north_m])
    up = relief_m * np.sin(en[:, 0] / 17.0) * np.cos(en[:, 1] / 23.0)
    points = np.column_stack([en, up])
    return project_points(CAM, pose, points) + rng.normal(0.0, sigma_px, (n, 2)), points


def test_project_points_on_the_plane_is_the_ground_homography() -> None:
    pose = CameraPose(3.0, -4.0, 120.0, 75.0, 5.0, -2.0)
    ground = np.random.default_rng(2).uniform(-40, 40, (20, 2))
    np.testing.assert_allclose(
        project_points(CAM, pose, ground), project_ground(CAM, pose, ground), atol=1e-9
    )


def test_refine_pose_on_terrain_recovers_what_a_plane_cannot() -> None:
    """12 m of relief under a camera at 65 m: the 3D points give the pose back to centimetres; the
    same pixels against the flat ground are metres off, which is the flat model's error."""
    true = CameraPose(5.0, 8.0, 65.0, 40.0, 6.0, -4.0)
    frame_px, points = terrain_correspondences(true, 0.7, relief_m=12.0)
    start = CameraPose(9.0, 4.0, 70.0, 44.0, 3.0, -1.0)
    pose, _, rms = refine_pose(CAM, frame_px, points, start)
    assert math.hypot(pose.east_m - true.east_m, pose.north_m - true.north_m) < 0.1
    assert rms == pytest.approx(math.sqrt(2) * 0.7, rel=0.2)
    *_, flat_rms = refine_pose(CAM, frame_px, points[:, :2], start)
    assert flat_rms > 3 * rms


@pytest.mark.parametrize("pitch_error_deg", [0.0, 0.5])
def test_a_soft_attitude_prior_helps_and_is_weighed_by_its_sigma(pitch_error_deg: float) -> None:
    """Few noisy points at a narrow view: the autopilot's attitude (1 deg) makes the position
    better than the image alone; its sigma bounds how far it can pull."""
    true = CameraPose(0.0, 0.0, 300.0, 10.0, 3.0, -2.0)
    frame_px, ground = noisy_correspondences(true, 2.0, n=25, seed=4)
    start = CameraPose(5.0, 5.0, 310.0, 12.0, 0.0, 0.0)
    _, free_cov, _ = refine_pose(CAM, frame_px, ground, start)
    prior = AttitudePrior(true.pitch_deg + pitch_error_deg, true.roll_deg, 1.0)
    held, held_cov, _ = refine_pose(CAM, frame_px, ground, start, attitude_prior=prior)
    assert held_cov.shape == (6, 6)
    assert np.sqrt(held_cov[4, 4]) < min(1.0, np.sqrt(free_cov[4, 4]))
    assert abs(held.pitch_deg - prior.pitch_deg) < 3 * np.sqrt(held_cov[4, 4]) + 1.0
    err = math.hypot(held.east_m - true.east_m, held.north_m - true.north_m)
    assert err < 3 * math.sqrt(held_cov[0, 0] + held_cov[1, 1])


# --- validation --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: Camera(640, 480, 0.0, 500.0, 320.0, 240.0), "fx"),
        (lambda: Camera(640, 480, 500.0, -500.0, 320.0, 240.0), "fy"),
        (lambda: Camera(640, 480, math.nan, 500.0, 320.0, 240.0), "fx"),
        (lambda: Camera(640, 480, 500.0, 500.0, 700.0, 240.0), "cx"),
        (lambda: Camera(640, 480, 500.0, 500.0, -1.0, 240.0), "cx"),
        (lambda: Camera(640, 480, 500.0, 500.0, 320.0, math.nan), "cy"),
        (lambda: Camera(0, 480, 500.0, 500.0, 0.0, 240.0), "width"),
        (lambda: Camera(640, 480, 500.0, 500.0, 320.0, 240.0, (0.1, 0.0, 0.0)), "distortion"),
        (lambda: Camera(640, 480, 500.0, 500.0, 320.0, 240.0, (0.1, 0.0, math.nan, 0.0, 0.0)), "distortion"),
        (lambda: Camera(640, 480, 0.5, 0.5, 320.0, 240.0), "field of view"),
        (lambda: Camera.from_hfov(640, 480, 0.0), "hfov"),
        (lambda: Camera.from_hfov(640, 480, 179.9), "hfov"),
        (lambda: Camera.from_hfov(640, 480, math.nan), "hfov"),
    ],
)
def test_invalid_camera_is_refused(make, field: str) -> None:
    """Impossible intrinsics raise OrthonavError naming the offending field."""
    with pytest.raises(OrthonavError, match=field):
        make()


@pytest.mark.parametrize(
    ("field", "value"), [("k1", -4.0), ("k2", 12.0), ("p1", 1.5), ("p2", -1.5), ("k3", 40.0)]
)
def test_a_distortion_term_no_lens_has_is_refused_naming_its_field(field: str, value: float) -> None:
    """Each term is bounded by how far it alone would move the image corner (twice its radius)."""
    coefficients = dict.fromkeys(DISTORTION_KEYS, 0.0) | {field: value}
    with pytest.raises(OrthonavError, match=rf"camera {field}: expected \|{field}\| <= "):
        Camera.from_dict({"width": 640, "height": 480, "hfov_deg": 60, **coefficients})


def test_strong_and_narrow_lens_distortions_are_within_the_bounds(seneca_camera: Camera) -> None:
    """A wide lens's strong barrel, a narrow lens's large high-order terms (powers of a small
    radius), and the self-calibrated real Seneca camera are all accepted."""
    Camera(640, 480, 380.0, 384.0, 322.0, 238.0, (-0.3, 0.1, 0.001, -0.0015, -0.01))
    Camera(1920, 1080, 9000.0, 9000.0, 960.0, 540.0, (0.5, -20.0, 0.0, 0.0, 800.0))
    assert any(seneca_camera.distortion)


# --- JSON --------------------------------------------------------------------------------------


def test_from_json_round_trip(tmp_path: Path) -> None:
    """to_dict -> JSON file -> from_json gives the same camera, distortion included."""
    cam = Camera(1024, 768, 800.0, 805.0, 510.0, 380.0, (-0.1, 0.02, 0.001, -0.002, 0.0))
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(cam.to_dict()))
    assert Camera.from_json(path) == cam
    path.write_bytes(b"\xff\xd8\xff\xe0 a JPEG, not a camera")
    with pytest.raises(OrthonavError, match="not a text file"):
        Camera.from_json(path)
    path.write_text(json.dumps({"width": 640, "height": 480, "hfov_deg": 60}))
    assert Camera.from_json(path) == CAM
    # As Windows editors save UTF-8: with a byte order mark first.
    path.write_bytes(codecs.BOM_UTF8 + json.dumps(cam.to_dict()).encode())
    assert Camera.from_json(path) == cam


@pytest.mark.parametrize(
    ("content", "expected"),
    [
        ('{"width": 640, "height": 480}', r"missing field 'hfov_deg' or 'fx'"),
        ('{"height": 480, "hfov_deg": 60}', r"missing field 'width'"),
        ('{"width": 640, "height": 480, "hfov_deg": 60, "k1": 0.1}', r"missing field 'k2'"),
        ('{"width": 640, "height": 480, "hfov_deg": 60', r"not valid JSON"),
        ("", r"not valid JSON"),
        ('{"width": 640, "height": 480, "hfov_deg": "wide"}', r"expected a finite number"),
        ('{"width": "big", "height": 480, "hfov_deg": 60}', r"expected a finite number"),
        ('{"width": 640, "height": null, "hfov_deg": 60}', r"expected a finite number"),
        ('{"width": 640, "height": 480, "hfov_deg": 200}', r"hfov_deg"),
        (
            '{"width": 640, "height": 480, "hfov_deg": 60, "k1": 1e30, "k2": 0, "p1": 0, "p2": 0, "k3": 0}',
            r"camera k1: expected \|k1\| <= 3\.\d+ for this camera, got 1e\+30",
        ),
        ('{"width": 640, "height": 480, "fx": -1, "fy": 500, "cx": 320, "cy": 240}', r"fx"),
        ("[640, 480, 60]", r"expected a JSON object"),
    ],
)
def test_from_json_errors_name_the_file(tmp_path: Path, content: str, expected: str) -> None:
    """Broken camera files raise OrthonavError naming the file and what is wrong."""
    path = tmp_path / "camera.json"
    path.write_text(content)
    with pytest.raises(OrthonavError, match=expected) as exc:
        Camera.from_json(path)
    assert str(path) in str(exc.value)


@pytest.mark.parametrize("kind", ["missing", "directory", "binary"])
def test_from_json_unreadable_file(tmp_path: Path, kind: str) -> None:
    """A missing file, a directory or binary junk is an OrthonavError naming the path, not an OSError."""
    path = tmp_path / "camera.json"
    if kind == "directory":
        path.mkdir()
    elif kind == "binary":
        path.write_bytes(bytes(range(128, 256)) * 4)
    with pytest.raises(Exception) as exc:
        Camera.from_json(path)
    assert type(exc.value) is OrthonavError, repr(exc.value)
    assert str(path) in str(exc.value)


# --- distortion --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "distortion",
    [
        (-0.1, 0.02, 0.0005, -0.0005, 0.0),  # mild barrel
        (-0.3, 0.1, 0.001, -0.0015, -0.01),  # strong barrel, wide lens
        (0.1, -0.05, 0.0, 0.0, 0.01),  # pincushion
    ],
)
def test_undistort_inverts_opencv_distortion(distortion: tuple[float, ...]) -> None:
    """undistort_points(cv2.projectPoints(ideal rays)) returns the ideal pixels to 1e-4 px."""
    cam = Camera(640, 480, 380.0, 384.0, 322.0, 238.0, distortion)
    xs, ys = np.meshgrid(np.linspace(0, 640, 17), np.linspace(0, 480, 13))
    ideal = np.column_stack([xs.ravel(), ys.ravel()])
    rays = np.column_stack(
        [(ideal[:, 0] - cam.cx) / cam.fx, (ideal[:, 1] - cam.cy) / cam.fy, np.ones(len(ideal))]
    )
    distorted, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, np.array(distortion))
    distorted = distorted.reshape(-1, 2)
    assert np.abs(distorted - ideal).max() > 5.0  # the lens does move points
    np.testing.assert_allclose(cam.undistort_points(distorted), ideal, atol=1e-4)


def test_a_camera_is_a_hashable_value_whatever_sequence_its_distortion_came_in() -> None:
    listed = Camera(640, 480, 380.0, 384.0, 322.0, 238.0, [-0.1, 0.02, 0.0, 0.0, 0.0])
    tupled = Camera(640, 480, 380.0, 384.0, 322.0, 238.0, (-0.1, 0.02, 0.0, 0.0, 0.0))
    assert listed.distortion == tupled.distortion and isinstance(listed.distortion, tuple)
    assert hash(listed) == hash(tupled) and listed == tupled


def test_undistort_without_distortion_is_identity() -> None:
    """No distortion: the points come back unchanged, as (N, 2) float."""
    pts = np.array([[1.5, 2.5], [600.0, 400.0]])
    out = CAM.undistort_points(pts)
    assert out.shape == (2, 2)
    np.testing.assert_array_equal(out, pts)


def test_scaled_camera_keeps_field_of_view() -> None:
    """Resizing the image by 0.5 halves the focal length and principal point, keeps the FOV."""
    cam = Camera(640, 480, 500.0, 510.0, 320.0, 240.0, (-0.1, 0.0, 0.0, 0.0, 0.0))
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    assert (half.fx, half.fy, half.cx, half.cy) == pytest.approx((250.0, 255.0, 160.0, 120.0))
    assert half.hfov_deg == pytest.approx(cam.hfov_deg)
    assert half.distortion == cam.distortion


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        ({"width": 1e400, "height": 480, "hfov_deg": 60}, "width: expected a finite number"),
        ({"width": 640.5, "height": 480, "hfov_deg": 60}, "width: expected a whole number of pixels"),
        ({"width": 640, "height": 480, "hfov_deg": True}, "hfov_deg: expected a finite number"),
        ({"width": "640", "height": 480, "hfov_deg": 60}, "width: expected a finite number"),
        (
            {"width": 640, "height": 480, "hfov_deg": 60, "fx": 800, "fy": 800, "cx": 320, "cy": 240},
            "disagrees",
        ),
        ({"width": 640, "height": 480, "fx": 800}, "missing field 'fy'"),
    ],
)
def test_camera_fields_are_checked_for_type_and_consistency(data: dict, fragment: str) -> None:
    with pytest.raises(OrthonavError, match=fragment):
        Camera.from_dict(data)


def test_full_intrinsics_win_over_a_consistent_hfov() -> None:
    """A calibrated principal point is kept when the file also states the field of view."""
    cam = Camera.from_dict(
        {
            "width": 1600,
            "height": 1200,
            "fx": 1147.36,
            "fy": 1147.36,
            "cx": 800.82,
            "cy": 602.26,
            "hfov_deg": 69.77,
        }
    )
    assert (cam.fx, cam.cx, cam.cy) == (1147.36, 800.82, 602.26)
    assert Camera.from_dict({"width": 640.0, "height": 480, "hfov_deg": 60}).width == 640
