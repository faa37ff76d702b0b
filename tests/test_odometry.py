"""Frame-to-frame motion (orthonav.odometry.estimate_motion) on frames rendered from the
synthetic terrain at known poses: displacement, heading change, their signs, and the errors."""

from __future__ import annotations

import math

import numpy as np
import pytest

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames.render import TruePose, render_frame
from orthonav.geo import GeoRaster, destination
from orthonav.odometry import Motion, OdometryError, estimate_motion

ALT_M = 300.0


def _pair(raster: GeoRaster, camera: Camera, yaw0: float, right_m: float, forward_m: float, dyaw: float):
    """Two frames: the second displaced by (right, forward) in the first one's axes and turned."""
    lat, lon = raster.center_latlon
    first = TruePose(lat, lon, ALT_M, yaw0)
    dist = math.hypot(right_m, forward_m)
    if dist > 0:
        lat, lon = destination(lat, lon, yaw0 + math.degrees(math.atan2(right_m, forward_m)), dist)
    second = TruePose(lat, lon, ALT_M, yaw0 + dyaw)
    return render_frame(raster, camera, first), render_frame(raster, camera, second)


@pytest.mark.parametrize(
    ("yaw0", "right_m", "forward_m", "dyaw"),
    [(30.0, 20.0, 0.0, 10.0), (200.0, -15.0, 10.0, -25.0), (0.0, 0.0, 40.0, 0.0)],
)
def test_motion_recovers_displacement_and_heading_change(
    terrain_raster, camera, yaw0, right_m, forward_m, dyaw
):
    previous, current = _pair(terrain_raster, camera, yaw0, right_m, forward_m, dyaw)
    motion = estimate_motion(previous, current, camera, ALT_M)
    assert isinstance(motion, Motion)
    gsd_m = camera.nadir_gsd_m(ALT_M)
    assert abs(motion.right_m - right_m) < 2 * gsd_m
    assert abs(motion.forward_m - forward_m) < 2 * gsd_m
    assert abs(motion.dyaw_deg - dyaw) < 0.3
    assert abs(motion.climb_m) < 1.0
    assert motion.inliers >= 100 and motion.inlier_ratio > 0.8
    assert motion.covariance.shape == (3, 3)
    assert np.all(np.linalg.eigvalsh(motion.covariance) > 0)
    # The altitude's scale uncertainty makes the error grow along a longer displacement.
    assert motion.covariance[1, 1] > motion.covariance[0, 0] if abs(forward_m) > abs(right_m) else True


def test_hovering_is_zero_motion_and_degenerate_for_the_essential_model(terrain_raster, camera):
    previous, current = _pair(terrain_raster, camera, 45.0, 0.0, 0.0, 0.0)
    motion = estimate_motion(previous, current, camera, ALT_M)
    assert motion.distance_m < 0.5 and abs(motion.dyaw_deg) < 0.1 and not motion.degenerate
    essential = estimate_motion(previous, current, camera, ALT_M, method="essential")
    assert essential.degenerate and essential.method == "homography"
    assert essential.distance_m < 0.5


def test_pure_rotation_keeps_the_position(terrain_raster, camera):
    previous, current = _pair(terrain_raster, camera, 90.0, 0.0, 0.0, 40.0)
    motion = estimate_motion(previous, current, camera, ALT_M)
    assert motion.distance_m < 1.0
    assert abs(motion.dyaw_deg - 40.0) < 0.3


def test_scale_follows_the_altitude(terrain_raster, camera):
    previous, current = _pair(terrain_raster, camera, 0.0, 0.0, 30.0, 0.0)
    low = estimate_motion(previous, current, camera, ALT_M / 2)
    assert low.forward_m == pytest.approx(15.0, abs=0.5)


def test_frames_without_overlap_are_refused(terrain_raster, camera):
    width_m, _ = camera.nadir_footprint_m(ALT_M)
    previous, current = _pair(terrain_raster, camera, 0.0, 1.2 * width_m, 0.0, 0.0)
    with pytest.raises(OdometryError, match="too few"):
        estimate_motion(previous, current, camera, ALT_M)


def test_textureless_frames_are_refused(camera):
    flat = np.full((camera.height, camera.width, 3), 120, np.uint8)
    with pytest.raises(OdometryError, match="too few feature matches"):
        estimate_motion(flat, flat, camera, ALT_M)


def test_bad_arguments_name_the_field(terrain_raster, camera):
    previous, current = _pair(terrain_raster, camera, 0.0, 0.0, 10.0, 0.0)
    assert issubclass(OdometryError, OrthonavError)
    with pytest.raises(OrthonavError, match="current frame: 320x240 px does not match"):
        estimate_motion(previous, current[::2, ::2], camera, ALT_M)
    with pytest.raises(OdometryError, match="alt_agl_m"):
        estimate_motion(previous, current, camera, float("nan"))
    with pytest.raises(OrthonavError, match="odometry method"):
        estimate_motion(previous, current, camera, ALT_M, method="optical-flow")
