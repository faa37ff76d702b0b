"""The flat-ground sigma measures the relief its inliers show, keeps its floor where they show none
with the tilt free, and with the tilt held by an attitude prior takes the image's pull on it."""

from __future__ import annotations

import numpy as np
import pytest

from orthonav.camera import AttitudePrior, Camera, CameraPose, pixel_to_ground, project_points, refine_pose
from orthonav.frames.relief import Relief, _ray_heights
from orthonav.localize.uncertainty import FlatGroundModel, held_tilt_deg, unexplained_m

CAMERA = Camera.from_hfov(640, 480, 60.0)
HEIGHT_M = 30.0


def _scene(rng: np.random.Generator, step_m: float) -> tuple[float, float]:
    """Inliers seen from 30 m with the tilt free: ground points, those on one side of the drone
    raised by ``step_m`` (roofs along one side of a street), 0.5 px of matcher noise. The
    flat-ground fit's position error and its sigma (the fit's own with the model's)."""
    truth = CameraPose(0.0, 0.0, HEIGHT_M, rng.uniform(0, 360), rng.uniform(-3, 3), rng.uniform(-3, 3))
    pixels = rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (200, 2))
    ground = pixel_to_ground(CAMERA, truth, pixels)
    side = np.array([np.cos(angle := rng.uniform(0, 2 * np.pi)), np.sin(angle)])
    heights = np.where(ground @ side > 0.0, step_m, 0.0)
    frame_px = project_points(CAMERA, truth, np.column_stack([ground, heights]))
    frame_px += rng.normal(0.0, 0.5, frame_px.shape)
    fitted, cov, _ = refine_pose(CAMERA, frame_px, ground, truth, robust=True, effective_points=20)
    model = FlatGroundModel()
    residual_m = unexplained_m(CAMERA, frame_px, ground, fitted, model.noise_px)
    sigma = np.hypot(
        model.sigma_m(CAMERA, fitted, residual_m, held_off_deg=None), np.sqrt(cov[0, 0] + cov[1, 1])
    )
    return float(np.hypot(fitted.east_m, fitted.north_m)), float(sigma)


def _errors_and_sigmas(step_m: float, scenes: int = 16) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(11)
    return tuple(np.array(v) for v in zip(*(_scene(rng, step_m) for _ in range(scenes)), strict=True))


def test_flat_ground_keeps_the_slope_floor() -> None:
    """Points on one plane: nothing unexplained beyond noise, so the model adds only the floor."""
    camera_pose = CameraPose(0.0, 0.0, HEIGHT_M, 0.0)
    model = FlatGroundModel()
    assert model.sigma_m(CAMERA, camera_pose, 0.0, held_off_deg=None) == pytest.approx(model.slope * HEIGHT_M)
    errors, sigmas = _errors_and_sigmas(0.0)
    assert np.all(errors < 0.2) and np.all(sigmas < 1.5 * model.slope * HEIGHT_M)


@pytest.mark.parametrize("step_m", [4.0, 8.0])
def test_roofs_on_one_side_are_covered_by_the_sigma(step_m: float) -> None:
    """Roofs a seventh to a quarter of the height on one side: the free tilt moves the camera by
    metres, and the sigma grows with them (the slope floor alone covered few of these)."""
    errors, sigmas = _errors_and_sigmas(step_m)
    floor = FlatGroundModel().slope * HEIGHT_M
    assert np.mean(errors <= 3.0 * floor) < 0.5  # what the fixed slope allowance would claim
    assert np.mean(errors <= 3.0 * sigmas) >= 0.9
    assert np.mean((errors / sigmas) ** 2) <= 4.0
    assert np.median(sigmas) <= 3.0 * np.percentile(errors, 95)


def test_a_held_tilt_takes_a_smaller_allowance() -> None:
    """With roll and pitch held by a prior, relief stays in the residuals instead of moving the
    camera: the same residuals weigh less."""
    model = FlatGroundModel()
    cam = CameraPose(0.0, 0.0, HEIGHT_M, 0.0)
    free, held = (model.sigma_m(CAMERA, cam, 1.0, held_off_deg=t) for t in (None, 3.0))
    assert free > held >= model.slope * HEIGHT_M


def _sloped_scene(rng: np.random.Generator, slope: float) -> tuple[float, float, float]:
    """Inliers on ground rising by ``slope`` one way, seen from 30 m with 0.5 px of matcher
    noise, roll and pitch held by an autopilot prior 0.3 deg off: the held flat-ground fit's
    position error, its sigma (the fit's own with the model's) and the model's allowance."""
    truth = CameraPose(0.0, 0.0, HEIGHT_M, rng.uniform(0, 360), rng.uniform(-3, 3), rng.uniform(-3, 3))
    ground = pixel_to_ground(CAMERA, truth, rng.uniform([0, 0], [CAMERA.width, CAMERA.height], (200, 2)))
    uphill = np.array([np.cos(angle := rng.uniform(0, 2 * np.pi)), np.sin(angle)])
    frame_px = project_points(CAMERA, truth, np.column_stack([ground, slope * ground @ uphill]))
    frame_px += rng.normal(0.0, 0.5, frame_px.shape)
    pitch, roll = rng.normal([truth.pitch_deg, truth.roll_deg], 0.3)
    prior = AttitudePrior(float(pitch), float(roll), 0.3)
    free, _, _ = refine_pose(CAMERA, frame_px, ground, truth, robust=True, effective_points=20)
    held, cov, _ = refine_pose(
        CAMERA, frame_px, ground, free, attitude_prior=prior, robust=True, effective_points=20
    )
    model = FlatGroundModel()
    residual_m = unexplained_m(CAMERA, frame_px, ground, held, model.noise_px)
    pull_deg = float(np.hypot(held.pitch_deg - pitch, held.roll_deg - roll))
    allowance = model.sigma_m(CAMERA, held, residual_m, held_tilt_deg(pull_deg, prior.sigma_deg))
    sigma = np.hypot(allowance, np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]))))
    return float(np.hypot(held.east_m, held.north_m)), float(sigma), allowance


@pytest.mark.parametrize("slope", [0.0, 0.02, 0.03])
def test_a_held_tilt_takes_the_slope_its_image_shows(slope: float) -> None:
    """With the tilt held, a slope moves the camera only as far as the image pulls the tilt from
    the autopilot's: level ground keeps a fraction of the fixed allowance (the prior's own error),
    sloped ground about what it moved, and both stay covered."""
    rng = np.random.default_rng(7)
    errors, sigmas, allowances = np.array([_sloped_scene(rng, slope) for _ in range(16)]).T
    floor = FlatGroundModel().slope * HEIGHT_M
    assert np.mean(errors <= 3.0 * sigmas) >= 0.9 and np.mean((errors / sigmas) ** 2) <= 4.0
    if slope == 0.0:
        assert np.median(allowances) < 0.5 * floor
    else:
        assert np.median(errors) > 0.5 * slope * HEIGHT_M  # the slope moved the camera
        assert np.median(allowances) > 0.5 * slope * HEIGHT_M


def test_a_ray_meets_the_box_it_passes_over_and_the_ground_elsewhere() -> None:
    """A 6 m box under the drone: the ray straight down meets its top; a ray far out, the ground."""
    half = 20.0
    grid = np.zeros((400, 400), np.float32)
    grid[180:220, 180:220] = 6.0  # 4 m square around the drone (0.1 m cells)
    ground = np.array([[0.0, 0.0], [15.0, 15.0]])
    hit = _ray_heights(ground, HEIGHT_M, grid, half, 10.0)
    assert hit[0] == pytest.approx(6.0, abs=0.25) and hit[1] == 0.0


def test_relief_boxes_cover_about_their_share() -> None:
    grid = Relief(cover=0.3).heights(50.0, np.random.default_rng(1))
    covered = float(np.mean(grid > 0))
    assert 0.1 < covered < 0.5 and grid.max() <= 10.0
