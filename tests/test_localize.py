"""Localizer accuracy, honesty and covariance on frames rendered at known true poses.

Truth comes from the pose each frame was rendered at: the drone position, and the ground
point under the image centre from the camera model (conftest.true_centre_latlon). Errors
are measured with pyproj geodesics. Expectations do not come from the localizer itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import pytest
from conftest import (
    NAIP_ALT_M,
    TERRAIN_ALT_M,
    NoisyPrior,
    angle_diff_deg,
    naip_path,
    noisy_prior,
    random_pose,
    true_centre_latlon,
)
from pyproj import Geod

from orthonav.camera import Camera, CameraPose, image_corners, pixel_to_ground
from orthonav.errors import OrthonavError
from orthonav.frames.render import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, LocalFrame, PixelWindow, destination, distance_m
from orthonav.localize import (
    Localizer,
    LocalizerConfig,
    all_tiles,
    motion_prediction,
    start_block,
    tiles_near,
)
from orthonav.mapdb import MapPackage
from orthonav.types import Fix, Pose, Prior

GEOD = Geod(ellps="WGS84")
BATCH = 20


# Frames rendered from the orthophoto see an exactly flat world: no unseen terrain slope to allow
# for, so the covariance must describe the error by the fit alone (real photos: test_real_photos).
FLAT_WORLD = LocalizerConfig(flat_slope=0.0)


@dataclass
class Trial:
    pose: TruePose
    noisy: NoisyPrior
    fix: Fix


def run_batch(
    package: MapPackage,
    raster: GeoRaster,
    camera: Camera,
    nominal_alt_m: float,
    seed: int,
    n: int = BATCH,
    with_prior: bool = True,
) -> list[Trial]:
    """Render ``n`` frames at random true poses (random photometric change) and localize them."""
    rng = np.random.default_rng(seed)
    localizer = Localizer(package, camera, FLAT_WORLD)
    trials = []
    for _ in range(n):
        pose = random_pose(rng, raster, camera, nominal_alt_m)
        frame = render_frame(raster, camera, pose, Photometric.random(rng), rng)
        noisy = noisy_prior(rng, pose) if with_prior else NoisyPrior(Prior(), 0.0)
        trials.append(Trial(pose, noisy, localizer.localize(frame, noisy.prior)))
    return trials


def error_enu(fix: Fix, pose: TruePose) -> np.ndarray:
    """True minus estimated drone position, (east, north) metres at the estimate."""
    east, north = LocalFrame(fix.pose.lat, fix.pose.lon).to_enu(pose.lat, pose.lon)
    return np.array([float(east), float(north)])


def centre_error_m(fix: Fix, camera: Camera, pose: TruePose) -> float:
    lat, lon = true_centre_latlon(camera, pose)
    return float(distance_m(lat, lon, fix.pose.centre_lat, fix.pose.centre_lon))


def summarize(label: str, trials: list[Trial], camera: Camera) -> None:
    ok = [t for t in trials if t.fix.accepted]
    print(f"\n{label}: {len(ok)}/{len(trials)} accepted")
    if ok:
        centre = [centre_error_m(t.fix, camera, t.pose) for t in ok]
        pos = [float(np.linalg.norm(error_enu(t.fix, t.pose))) for t in ok]
        print(
            f"  centre error median {np.median(centre):.2f} m, max {max(centre):.2f} m; "
            f"position error median {np.median(pos):.2f} m, max {max(pos):.2f} m"
        )


def mahalanobis(fix: Fix, pose: TruePose) -> float:
    d = error_enu(fix, pose)
    return float(math.sqrt(d @ np.linalg.solve(fix.covariance_enu_m2, d)))


# --- fixtures: one batch per scenario, shared by the assertions below ---------------------


@pytest.fixture(scope="module")
def terrain_trials(terrain_map, terrain_raster, camera) -> list[Trial]:
    trials = run_batch(terrain_map, terrain_raster, camera, TERRAIN_ALT_M, seed=11)
    summarize("synthetic terrain, with priors", trials, camera)
    return trials


@pytest.fixture(scope="module")
def naip_trials(naip_map, naip_raster, camera) -> list[Trial]:
    trials = run_batch(naip_map, naip_raster, camera, NAIP_ALT_M, seed=12)
    summarize("NAIP 2020 on the 2020 map, with priors", trials, camera)
    return trials


SCENARIOS = ["terrain_trials", "naip_trials"]


def _scenario(request: pytest.FixtureRequest, name: str) -> tuple[list[Trial], MapPackage]:
    trials = request.getfixturevalue(name)
    package = request.getfixturevalue("terrain_map" if name.startswith("terrain") else "naip_map")
    return trials, package


# --- accuracy with priors -----------------------------------------------------------------


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_most_same_date_frames_are_fixed(request: pytest.FixtureRequest, scenario: str) -> None:
    """With position, heading, altitude and attitude priors, at least 90 % of the frames are fixed."""
    trials, _ = _scenario(request, scenario)
    accepted = sum(t.fix.accepted for t in trials)
    assert accepted >= 0.9 * len(trials), [t.fix.reason for t in trials if not t.fix.accepted]


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_frame_centre_within_two_map_pixels(
    request: pytest.FixtureRequest, scenario: str, camera: Camera
) -> None:
    """The ground point under the image centre is found within 2 map pixels of the truth."""
    trials, package = _scenario(request, scenario)
    errors = [centre_error_m(t.fix, camera, t.pose) for t in trials if t.fix.accepted]
    assert errors
    assert max(errors) <= 2.0 * package.gsd_m, errors


def test_frame_centre_is_unbiased(
    terrain_trials: list[Trial], terrain_map: MapPackage, camera: Camera
) -> None:
    """No systematic offset (e.g. a half-pixel convention slip) in map pixels: mean |bias| < 0.15 px."""
    offsets = []
    for t in terrain_trials:
        if t.fix.accepted:
            true_col, true_row = terrain_map.grid.latlon_to_pixel(*true_centre_latlon(camera, t.pose))
            col, row = terrain_map.grid.latlon_to_pixel(t.fix.pose.centre_lat, t.fix.pose.centre_lon)
            offsets.append((float(col - true_col), float(row - true_row)))
    bias = np.mean(offsets, axis=0)
    assert np.all(np.abs(bias) < 0.15), f"mean offset (col, row) {bias} map px"


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_drone_position_error_is_explained_by_the_attitude_prior(
    request: pytest.FixtureRequest, scenario: str
) -> None:
    """With pitch/roll taken from the prior, the point under the drone is off by about h tan(e).

    e is the (known) AHRS error of that frame; the centre is within 2 map px (test above),
    so the drone position must be within h tan(e) (+10 % for the tilt geometry) + 2 map px.
    """
    trials, package = _scenario(request, scenario)
    for t in trials:
        if t.fix.accepted:
            bound = 1.1 * t.pose.alt_agl_m * math.tan(math.radians(t.noisy.attitude_error_deg))
            bound += 2.0 * package.gsd_m
            error = float(np.linalg.norm(error_enu(t.fix, t.pose)))
            assert error <= bound, (error, bound, t.pose)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_heading_and_altitude_are_recovered(request: pytest.FixtureRequest, scenario: str) -> None:
    """Heading within 1 deg (the prior was up to 10 deg off), altitude within 3 %."""
    trials, _ = _scenario(request, scenario)
    for t in trials:
        if t.fix.accepted:
            assert angle_diff_deg(t.fix.pose.heading_deg, t.pose.yaw_deg) < 1.0
            assert abs(t.fix.pose.alt_agl_m / t.pose.alt_agl_m - 1.0) < 0.03


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_covariance_is_positive_definite_and_consistent(
    request: pytest.FixtureRequest, scenario: str
) -> None:
    """Accepted fixes carry a symmetric PD 2x2 covariance that neither under- nor over-states the error.

    For a 2-D Gaussian, P(Mahalanobis distance > 3) is 1 %, and the median distance is 1.18.
    """
    trials, _ = _scenario(request, scenario)
    distances = []
    for t in trials:
        if t.fix.accepted:
            cov = t.fix.covariance_enu_m2
            assert cov.shape == (2, 2)
            np.testing.assert_allclose(cov, cov.T)
            assert np.all(np.linalg.eigvalsh(cov) > 0)
            distances.append(mahalanobis(t.fix, t.pose))
    print(f"\n{scenario}: Mahalanobis distances {np.round(sorted(distances), 2).tolist()}")
    assert np.mean(np.asarray(distances) < 3.0) >= 0.9
    assert 0.3 < np.median(distances) < 2.5


# --- no prior at all ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("map_name", "raster_name", "nominal", "min_rate"),
    [("terrain_map", "terrain_raster", TERRAIN_ALT_M, 0.9), ("naip_map", "naip_raster", NAIP_ALT_M, 0.5)],
)
def test_same_date_frames_without_any_prior(
    request: pytest.FixtureRequest,
    camera: Camera,
    map_name: str,
    raster_name: str,
    nominal: float,
    min_rate: float,
) -> None:
    """No position, heading, altitude or attitude: matched against every tile, fixes are still right.

    The synthetic map has texture everywhere; real farmland has fields and lakes where the
    inlier ratio over all tiles is low, so only half of the NAIP frames must be fixed.
    """
    package = request.getfixturevalue(map_name)
    trials = run_batch(
        package, request.getfixturevalue(raster_name), camera, nominal, seed=21, with_prior=False
    )
    summarize(f"{map_name}, no prior", trials, camera)
    ok = [t for t in trials if t.fix.accepted]
    assert len(ok) >= min_rate * len(trials), [t.fix.reason for t in trials if not t.fix.accepted]
    for t in ok:
        assert centre_error_m(t.fix, camera, t.pose) <= 2.0 * package.gsd_m
        assert angle_diff_deg(t.fix.pose.heading_deg, t.pose.yaw_deg) < 1.0
        assert abs(t.fix.pose.alt_agl_m / t.pose.alt_agl_m - 1.0) < 0.03
        # Tilt is estimated from the homography too: the drone is off by h tan(tilt error),
        # with the tilt error below 2 deg.
        assert np.linalg.norm(error_enu(t.fix, t.pose)) < t.pose.alt_agl_m * math.tan(math.radians(2.0))
    # The fit's own covariance (no attitude prior to lean on) must still describe the error.
    distances = np.array([mahalanobis(t.fix, t.pose) for t in ok])
    assert np.mean(distances < 3.0) >= 0.9
    assert 0.3 < np.median(distances) < 2.5


# --- frames cut straight out of the orthophoto (no renderer involved) ---------------------


@pytest.mark.parametrize("quarter_turns", [0, 1, 2, 3])
def test_exact_crop_of_the_map_is_located_to_a_fraction_of_a_pixel(
    terrain_map: MapPackage, terrain_raster: GeoRaster, camera: Camera, quarter_turns: int
) -> None:
    """A frame that IS the orthophoto (pixel for pixel, turned by k x 90 deg) seen from straight above.

    At altitude fx x gsd one frame pixel is one map pixel; the camera is over the crop centre
    and its heading is k x 90 deg plus the grid convergence (the azimuth of the map's "up").
    """
    rng = np.random.default_rng(quarter_turns)
    w, h = (camera.width, camera.height) if quarter_turns % 2 == 0 else (camera.height, camera.width)
    col0, row0 = (int(v) for v in rng.integers(100, 1024 - 100 - max(w, h), 2))
    crop = terrain_raster.read_rgb(PixelWindow(col0, row0, w, h))
    frame = cv2.cvtColor(np.ascontiguousarray(np.rot90(crop, quarter_turns)), cv2.COLOR_RGB2BGR)
    lat, lon = terrain_raster.pixel_to_latlon(col0 + w / 2, row0 + h / 2)
    up_lat, up_lon = terrain_raster.pixel_to_latlon(col0 + w / 2, row0 + h / 2 - 100)
    grid_north, _, _ = GEOD.inv(float(lon), float(lat), float(up_lon), float(up_lat))
    heading = (90.0 * quarter_turns + grid_north) % 360.0
    alt = camera.fx * terrain_raster.gsd_m
    # The crop is seen exactly from above: the attitude is known to a hair.
    prior = Prior(
        alt_agl_m=alt, heading_deg=90.0 * quarter_turns, pitch_deg=0.0, roll_deg=0.0, attitude_sigma_deg=0.01
    )

    fix = Localizer(terrain_map, camera).localize(frame, prior)

    assert fix.accepted, fix.reason
    assert float(distance_m(lat, lon, fix.pose.lat, fix.pose.lon)) < 0.25 * terrain_map.gsd_m
    assert angle_diff_deg(fix.pose.heading_deg, heading) < 0.2
    assert abs(fix.pose.alt_agl_m / alt - 1.0) < 0.01


# --- cross-date: honesty over fix rate ----------------------------------------------------


@pytest.mark.parametrize("year", ["20090818", "20180716"])
@pytest.mark.parametrize("position_prior", [True, False], ids=["prior", "no-position"])
def test_cross_date_false_fixes_are_rare(
    naip_map: MapPackage, camera: Camera, year: str, position_prior: bool
) -> None:
    """Frames from another year against the 2020 map: whatever the fix rate, accepted fixes are right.

    A false fix is accepted but more than 50 m from the truth; at most 1 in 20 is tolerated.
    """
    rng = np.random.default_rng(int(year[:4]) + position_prior)
    localizer = Localizer(naip_map, camera)
    accepted, false_fixes = 0, []
    with GeoRaster(naip_path(year)) as frames:
        for _ in range(BATCH):
            pose = random_pose(rng, frames, camera, NAIP_ALT_M)
            frame = render_frame(frames, camera, pose, Photometric.random(rng, 0.5), rng)
            prior = noisy_prior(rng, pose, position=position_prior).prior
            fix = localizer.localize(frame, prior)
            if fix.accepted:
                accepted += 1
                error = float(distance_m(pose.lat, pose.lon, fix.pose.lat, fix.pose.lon))
                if error > 50.0:
                    false_fixes.append(round(error))
    print(
        f"\nNAIP {year} frames on the 2020 map ({'with' if position_prior else 'without'} position prior): "
        f"fix rate {accepted}/{BATCH}, false fixes {false_fixes}"
    )
    assert len(false_fixes) <= 1, false_fixes


# --- candidate tiles ----------------------------------------------------------------------


def _tile_centres(package: MapPackage) -> tuple[np.ndarray, np.ndarray]:
    centres = package.tiles.corners_latlon[:, 2]
    return centres[:, 0], centres[:, 1]


def _tiles_containing(package: MapPackage, lat: float, lon: float) -> set[int]:
    col, row = package.grid.latlon_to_pixel(lat, lon)
    box = package.tiles.box_px
    inside = (box[:, 0] <= col) & (col < box[:, 2]) & (box[:, 1] <= row) & (row < box[:, 3])
    return set(np.flatnonzero(inside).tolist())


def test_all_tiles_lists_every_tile(naip_map: MapPackage) -> None:
    assert all_tiles(naip_map).tolist() == list(range(len(naip_map)))


def test_tiles_near_is_sorted_by_distance_and_complete(naip_map: MapPackage) -> None:
    """Nearest first (pyproj distance to the tile centres); every tile whose centre is in range is there."""
    lat, lon = naip_map.grid.center_latlon
    radius = 1500.0
    found = tiles_near(naip_map, lat, lon, radius)
    clat, clon = _tile_centres(naip_map)
    dist = np.asarray(distance_m(np.full(len(clat), lat), np.full(len(clat), lon), clat, clon))
    assert len(set(found.tolist())) == len(found)
    assert np.all(np.diff(dist[found]) >= -1.0)  # metres; pixel vs geodesic distance rounding
    assert set(np.flatnonzero(dist <= radius).tolist()) <= set(found.tolist())
    tile_m = (naip_map.tiles.box_px[0, 2] - naip_map.tiles.box_px[0, 0]) * naip_map.gsd_m
    assert np.all(dist[found] <= radius + tile_m / math.sqrt(2) + 1.0)


@pytest.mark.parametrize("m", [1, 3])
def test_start_block_is_the_m_by_m_block_around_the_start_tile(naip_map: MapPackage, m: int) -> None:
    """The block is m x m contiguous grid cells centred on the tile whose centre is nearest the start."""
    rc = naip_map.tiles.grid_rc
    rows, cols = rc[:, 0].max() + 1, rc[:, 1].max() + 1
    inner = np.flatnonzero((rc[:, 0] > 0) & (rc[:, 0] < rows - 1) & (rc[:, 1] > 0) & (rc[:, 1] < cols - 1))
    clat, clon = _tile_centres(naip_map)
    centre_tile = int(inner[0])
    # A start point 100 m off that tile's centre: its centre is still the nearest one.
    lat, lon = destination(float(clat[centre_tile]), float(clon[centre_tile]), 30.0, 100.0)
    dist = np.asarray(distance_m(np.full(len(clat), lat), np.full(len(clat), lon), clat, clon))
    assert int(np.argmin(dist)) == centre_tile

    block = start_block(naip_map, lat, lon, m)

    assert len(block) == m * m
    r0, c0 = rc[centre_tile]
    expected = {
        (r0 + dr, c0 + dc) for dr in range(-(m // 2), m // 2 + 1) for dc in range(-(m // 2), m // 2 + 1)
    }
    assert {tuple(rc[i]) for i in block} == expected


def test_start_block_at_a_map_corner_is_cut_by_the_edge(naip_map: MapPackage) -> None:
    """At the top-left tile a 3 x 3 block keeps only the 2 x 2 tiles that exist."""
    rc = naip_map.tiles.grid_rc
    corner = int(np.flatnonzero((rc[:, 0] == 0) & (rc[:, 1] == 0))[0])
    clat, clon = _tile_centres(naip_map)
    block = start_block(naip_map, float(clat[corner]), float(clon[corner]), 3)
    assert {tuple(rc[i]) for i in block} == {(0, 0), (0, 1), (1, 0), (1, 1)}


@pytest.mark.parametrize("bearing", [0.0, 75.0, 200.0])
def test_motion_prediction_includes_the_tiles_under_the_predicted_points(
    naip_map: MapPackage, bearing: float
) -> None:
    """Every tile under the start and under each predicted point (bearing +- deviations) is a candidate."""
    lat, lon = naip_map.grid.center_latlon
    distance, deviations = 600.0, (-30.0, 0.0, 30.0)
    found = set(motion_prediction(naip_map, lat, lon, bearing, distance, 100.0, deviations).tolist())
    expected = _tiles_containing(naip_map, lat, lon)
    for dev in deviations:
        expected |= _tiles_containing(naip_map, *destination(lat, lon, bearing + dev, distance))
    assert expected
    assert expected <= found
    assert len(found) < len(naip_map)  # a prediction, not every tile


def test_motion_prediction_follows_the_bearing(naip_map: MapPackage) -> None:
    """Flying east, the candidates lie east of the start more than west of it."""
    lat, lon = naip_map.grid.center_latlon
    col, _ = naip_map.grid.latlon_to_pixel(lat, lon)
    found = motion_prediction(naip_map, lat, lon, 90.0, 1500.0, 50.0, (0.0,))
    box = naip_map.tiles.box_px[found]
    centre_cols = (box[:, 0] + box[:, 2]) / 2
    assert np.mean(centre_cols > col) > 0.5


def test_a_rejected_fix_never_carries_a_position_in_its_record() -> None:
    """The pose a fix was rejected with is kept for diagnosis, but not in the position fields."""
    pose = Pose(47.0, -99.0, 1000.0, 10.0, 1.0, -1.0, 47.001, -99.001)
    record = Fix(False, "reprojection RMSE too high", pose=pose).to_dict()
    assert all(record[k] is None for k in ("lat", "lon", "altitude", "heading", "centre_lat", "centre_lon"))
    assert record["rejected_pose"]["lat"] == 47.0
    accepted = Fix(True, pose=pose, covariance_enu_m2=np.eye(2)).to_dict()
    assert accepted["lat"] == 47.0 and "rejected_pose" not in accepted


def test_pose_footprint_corners_are_the_image_corners_on_the_ground(camera: Camera) -> None:
    """Footprint by ray casting agrees with the ground homography at the four image corners."""
    lat0, lon0 = 47.02, -99.15
    truth = CameraPose(0.0, 0.0, 800.0, 123.0, 4.0, -3.0)
    ground = pixel_to_ground(camera, truth, image_corners(camera))
    lat, lon = LocalFrame(lat0, lon0).to_latlon(ground[:, 0], ground[:, 1])
    pose = Pose(lat0, lon0, truth.alt_agl_m, truth.yaw_deg, truth.pitch_deg, truth.roll_deg, lat0, lon0)
    corners = pose.footprint_latlon(camera)
    assert np.all(distance_m(corners[:, 0], corners[:, 1], lat, lon) < 0.01)


def test_quick_matching_needs_float_descriptors(naip_map: MapPackage, camera: Camera) -> None:
    """Mutual nearest cosines mean nothing for ORB's binary descriptors: asking for them is an
    error that says so (the default asks only for learned matchers')."""
    with pytest.raises(OrthonavError, match="binary"):
        Localizer(naip_map, camera, LocalizerConfig(quick=True))
    assert not Localizer(naip_map, camera).descriptors_first
    with pytest.raises(OrthonavError, match="quick_ratio"):
        LocalizerConfig(quick_ratio=1.5)


def test_the_pose_is_refined_on_enough_points_whatever_the_inlier_gate() -> None:
    """``pose_points`` bounds the points a pose is refined on: fewer than a pose's six unknowns is
    refused by name; a gate that asks more inliers than that bound (a deliberately strict
    localizer) is a valid config, as the inliers are counted before the pose takes its share."""
    with pytest.raises(OrthonavError, match="pose_points 5: expected None or at least 6"):
        LocalizerConfig(pose_points=5)
    assert LocalizerConfig(min_inliers=100_000).pose_points < 100_000
    assert LocalizerConfig(pose_points=None).pose_points is None
