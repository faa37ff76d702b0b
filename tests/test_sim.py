"""Simulation: frame rendering geometry, photometric change, and the mission loop with its outputs."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from affine import Affine
from conftest import TERRAIN_ALT_M
from pyproj import CRS, Geod

from orthonav.camera import Camera, CameraPose, project_ground
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame, sees_only_ground
from orthonav.geo import GeoRaster, LocalFrame, PixelWindow, distance_m
from orthonav.mapdb import MapPackage
from orthonav.sim import MissionConfig, run_mission

# UTM 33N with the map centred on the zone's central meridian (15 E): grid north = true north,
# so a north-up crop of the raster is what a camera heading north sees.
UTM33 = CRS.from_epsg(32633)
ORIGIN_E, ORIGIN_N = 500_000.0 - 512.0, 5_600_000.0 + 512.0
MAP_PX = 1024
GEOD = Geod(ellps="WGS84")
BACKGROUND = 60


def write_map(path: Path, rgb: np.ndarray) -> Path:
    """A north-up 1 m/px GeoTIFF centred on UTM 33N's central meridian."""
    with rasterio.open(
        path,
        "w",
        driver="GTiff",
        width=rgb.shape[1],
        height=rgb.shape[0],
        count=3,
        dtype="uint8",
        crs=UTM33,
        transform=Affine(1.0, 0.0, ORIGIN_E, 0.0, -1.0, ORIGIN_N),
    ) as dst:
        dst.write(np.moveaxis(rgb, -1, 0))
    return path


@pytest.fixture(scope="module")
def marker_map(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, tuple[float, float]]:
    """Flat gray with one bright 7 x 7 px square; returns the file and the square's centre (col, row)."""
    rgb = np.full((MAP_PX, MAP_PX, 3), BACKGROUND, np.uint8)
    rgb[597:604, 447:454] = 255  # pixels 447..453, 597..603: centre at raster coordinates (450.5, 600.5)
    return write_map(tmp_path_factory.mktemp("marker") / "marker.tif", rgb), (450.5, 600.5)


@pytest.fixture(scope="module")
def texture_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Smooth random texture: interpolation between pixel centres changes little."""
    rng = np.random.default_rng(3)
    noise = rng.uniform(0, 255, (MAP_PX, MAP_PX, 3)).astype(np.float32)
    rgb = np.clip(cv2.GaussianBlur(noise, (0, 0), 2.0) * 4 - 382, 0, 255).astype(np.uint8)
    return write_map(tmp_path_factory.mktemp("texture") / "texture.tif", rgb)


def marker_centroid(frame: np.ndarray) -> np.ndarray:
    """Brightness-weighted centroid of the marker, in camera coordinates (pixel centres at +0.5)."""
    weight = np.clip(frame[..., 0].astype(float) - BACKGROUND, 0, None)
    assert weight.sum() > 0, "marker not in the frame"
    rows, cols = np.indices(weight.shape)
    return np.array([(cols * weight).sum(), (rows * weight).sum()]) / weight.sum() + 0.5


@pytest.mark.parametrize("yaw", [0.0, 90.0, 33.0, 217.0])
@pytest.mark.parametrize(
    ("gsd_m", "pitch", "roll"), [(0.5, 0.0, 0.0), (1.0, 0.0, 0.0), (2.0, 0.0, 0.0), (1.0, 6.0, -4.0)]
)
def test_render_puts_a_ground_point_where_the_camera_model_projects_it(
    marker_map: tuple[Path, tuple[float, float]],
    camera: Camera,
    yaw: float,
    gsd_m: float,
    pitch: float,
    roll: float,
) -> None:
    """A marker on the map appears in the frame at the pixel the pinhole model gives, to 0.15 px."""
    path, (col, row) = marker_map
    with GeoRaster(path) as raster:
        lat, lon = raster.pixel_to_latlon(430.0, 590.0)  # 20 m west, 10 m north of the marker
        pose = TruePose(float(lat), float(lon), camera.fx * gsd_m, yaw, pitch, roll)
        frame = render_frame(raster, camera, pose)
        mlat, mlon = raster.pixel_to_latlon(col, row)
    east, north = LocalFrame(pose.lat, pose.lon).to_enu(mlat, mlon)
    expected = project_ground(
        camera, CameraPose(0, 0, pose.alt_agl_m, yaw, pitch, roll), np.array([[east, north]])
    )
    np.testing.assert_allclose(marker_centroid(frame), expected[0], atol=0.15)


def test_a_lens_distortion_moves_the_marker_where_opencvs_model_puts_it(
    marker_map: tuple[Path, tuple[float, float]], camera: Camera
) -> None:
    """With distortion, the marker lands at the pinhole pixel distorted by OpenCV's own model, to
    0.3 px; rendering again (the per-camera pixel grid then cached) gives the same frame."""
    lens = replace(camera, distortion=(-0.2, 0.05, 0.001, -0.001, 0.0))
    path, (col, row) = marker_map
    with GeoRaster(path) as raster:
        lat, lon = raster.pixel_to_latlon(250.0, 450.0)  # the marker near the frame's edge
        pose = TruePose(float(lat), float(lon), lens.fx * 1.0, 33.0, 3.0, -2.0)
        frame, again = render_frame(raster, lens, pose), render_frame(raster, lens, pose)
        mlat, mlon = raster.pixel_to_latlon(col, row)
    east, north = LocalFrame(pose.lat, pose.lon).to_enu(mlat, mlon)
    ideal = project_ground(lens, CameraPose(0, 0, pose.alt_agl_m, 33.0, 3.0, -2.0), np.array([[east, north]]))
    ray = np.array([[(ideal[0, 0] - lens.cx) / lens.fx, (ideal[0, 1] - lens.cy) / lens.fy, 1.0]])
    expected, _ = cv2.projectPoints(ray, np.zeros(3), np.zeros(3), lens.K, np.array(lens.distortion))
    assert np.hypot(*(expected.reshape(2) - ideal[0])) > 3.0  # the lens does move it
    np.testing.assert_allclose(marker_centroid(frame), expected.reshape(2), atol=0.3)
    np.testing.assert_array_equal(frame, again)


def test_heading_north_nadir_frame_is_the_north_up_crop(texture_map: Path, camera: Camera) -> None:
    """Heading 0, nadir, one frame pixel per map pixel: the frame equals the raster crop around the drone.

    Rotated (180 deg) or mirrored crops must not match: the test tells the orientations apart.
    """
    with GeoRaster(texture_map) as raster:
        col, row = 512, 512
        lat, lon = raster.pixel_to_latlon(col, row)
        east_lat, east_lon = raster.pixel_to_latlon(col + 100, row)
        # One frame pixel = one raster pixel on the ground (a UTM metre is 1/0.9996 true metres here).
        pixel_m = GEOD.inv(float(lon), float(lat), float(east_lon), float(east_lat))[2] / 100.0
        assert pixel_m == pytest.approx(1.0 / 0.9996, rel=1e-5)
        pose = TruePose(float(lat), float(lon), camera.fx * pixel_m, 0.0)
        frame = cv2.cvtColor(render_frame(raster, camera, pose), cv2.COLOR_BGR2RGB).astype(float)
        crop = raster.read_rgb(PixelWindow(col - 320, row - 240, 640, 480)).astype(float)
    assert frame.shape == crop.shape == (480, 640, 3)
    diff = np.abs(frame - crop).mean()
    assert diff < 1.0
    assert np.abs(frame - crop[::-1, ::-1]).mean() > 20 * max(diff, 0.5)
    assert np.abs(frame - crop[:, ::-1]).mean() > 20 * max(diff, 0.5)


def test_render_is_deterministic_and_shaped_like_the_camera(
    terrain_raster: GeoRaster, camera: Camera
) -> None:
    lat, lon = terrain_raster.center_latlon
    pose = TruePose(lat, lon, 300.0, 45.0, 2.0, -1.0)
    a, b = render_frame(terrain_raster, camera, pose), render_frame(terrain_raster, camera, pose)
    assert a.shape == (camera.height, camera.width, 3) and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    assert a.std() > 10  # textured, not blank


def test_a_view_with_the_horizon_in_it_is_refused_not_drawn(terrain_raster: GeoRaster) -> None:
    """The pose a plane's 60 deg body camera crashed OpenCV's warp at (bank 67 deg, pitch 11 deg:
    sky in the frame's corner) raises a message naming the attitude; 45 deg of bank renders."""
    camera = Camera.from_hfov(640, 480, 60.0)
    lat, lon = terrain_raster.center_latlon
    banked = TruePose(lat, lon, 315.0, 30.0, 11.0, 45.0)
    assert sees_only_ground(camera, banked)
    assert render_frame(terrain_raster, camera, banked).std() > 10
    past = replace(banked, roll_deg=67.0)
    assert not sees_only_ground(camera, past)
    with pytest.raises(OrthonavError, match=r"roll 67\.0 deg puts the horizon in view"):
        render_frame(terrain_raster, camera, past)


# --- photometric change -------------------------------------------------------------------


def test_photometric_random_changes_the_image_but_not_its_shape(
    terrain_raster: GeoRaster, camera: Camera
) -> None:
    lat, lon = terrain_raster.center_latlon
    pose = TruePose(lat, lon, 300.0, 0.0)
    clean = render_frame(terrain_raster, camera, pose)
    rng = np.random.default_rng(5)
    changes = [Photometric.random(rng) for _ in range(3)]
    assert len({c.to_dict()["gamma"] for c in changes}) == 3  # random draws differ
    for change in changes:
        changed = render_frame(terrain_raster, camera, pose, change, np.random.default_rng(1))
        assert changed.shape == clean.shape and changed.dtype == np.uint8
        assert np.abs(changed.astype(float) - clean).mean() > 2.0
        # Still the same scene: strongly correlated with the clean frame.
        assert np.corrcoef(changed.mean(axis=2).ravel(), clean.mean(axis=2).ravel())[0, 1] > 0.5


def test_photometric_of_strength_zero_is_the_identity(terrain_raster: GeoRaster, camera: Camera) -> None:
    lat, lon = terrain_raster.center_latlon
    clean = render_frame(terrain_raster, camera, TruePose(lat, lon, 300.0, 0.0))
    none = Photometric.random(np.random.default_rng(0), strength=0.0)
    np.testing.assert_array_equal(none.apply(clean, np.random.default_rng(0)), clean)


def test_photometric_brightness_and_gain_act_in_the_documented_direction() -> None:
    """out = gain * ((in/255)^gamma * contrast + brightness), gains given as (R, G, B) on BGR images."""
    image = np.full((4, 4, 3), 100, np.uint8)
    out = Photometric(brightness=0.1, colour_gain=(1.2, 1.0, 0.8)).apply(image, np.random.default_rng(0))
    base = 100 / 255 + 0.1
    np.testing.assert_allclose(out[0, 0], np.round(np.array([0.8, 1.0, 1.2]) * base * 255), atol=1)


# --- the mission loop ---------------------------------------------------------------------


def _diagonal(package: MapPackage, a: float, b: float) -> tuple[tuple[float, float], tuple[float, float]]:
    lat, lon = package.grid.pixel_to_latlon(
        [a * package.grid.width, b * package.grid.width], [a * package.grid.height, b * package.grid.height]
    )
    return (float(lat[0]), float(lon[0])), (float(lat[1]), float(lon[1]))


@pytest.fixture(scope="module")
def mission(terrain_map: MapPackage, terrain_raster: GeoRaster, camera: Camera, tmp_path_factory):
    start, target = _diagonal(terrain_map, 0.25, 0.8)
    config = MissionConfig(*start, *target, speed_mps=20.0, step_s=5.0, arrival_radius_m=40.0, seed=4)
    run_dir = tmp_path_factory.mktemp("mission") / "run"
    result = run_mission(terrain_map, terrain_raster, camera, config, run_dir, progress=False)
    return config, result, run_dir


def test_mission_arrives_with_accurate_fixes(mission) -> None:
    config, result, run_dir = mission
    summary = json.loads((run_dir / "summary.json").read_text())
    print(f"\nmission summary: {summary}")
    assert summary["arrived"] is True and result.arrived
    assert summary["fix_rate"] >= 0.8
    assert summary["error_median_m"] is not None and summary["error_median_m"] < 5.0
    # Arrived by estimate: the true end point is within the arrival radius plus that fix's error.
    steps = [json.loads(line) for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    assert summary["true_distance_to_target_m"] <= config.arrival_radius_m + steps[-1]["nav_error_m"] + 1.0
    assert summary["arrived_true"] == (summary["true_distance_to_target_m"] <= config.arrival_radius_m)
    # It flew towards the target: the straight-line distance bounds the number of steps from below.
    direct = float(distance_m(config.start_lat, config.start_lon, config.target_lat, config.target_lon))
    min_steps = (direct - config.start_zone_m - config.arrival_radius_m) / (config.speed_mps * config.step_s)
    assert min_steps <= summary["steps"] <= 3 * min_steps + 3


def test_mission_step_log_has_one_consistent_record_per_step(mission) -> None:
    config, result, run_dir = mission
    lines = (run_dir / "steps.jsonl").read_text().splitlines()
    steps = [json.loads(line) for line in lines]
    assert len(steps) == result.steps == json.loads((run_dir / "summary.json").read_text())["steps"]
    assert [s["step"] for s in steps] == list(range(len(steps)))
    for s in steps:
        for key in (
            "true_lat",
            "true_lon",
            "est_lat",
            "est_lon",
            "error_m",
            "accepted",
            "reason",
            "nav_error_m",
        ):
            assert key in s
        assert s["time_s"] == pytest.approx(s["step"] * config.step_s)
        assert set(s["fix"]["timings"]) >= {"extract_ms", "total_ms"}
        if s["accepted"]:
            assert s["reason"] == ""
            recomputed = float(distance_m(s["true_lat"], s["true_lon"], s["est_lat"], s["est_lon"]))
            assert s["error_m"] == pytest.approx(recomputed, abs=1e-6)
        else:
            assert s["reason"] and s["est_lat"] is None and s["error_m"] is None
    # True positions advance by speed x step between frames: exactly on straight legs, less in turns.
    hops = np.array(
        [
            float(distance_m(a["true_lat"], a["true_lon"], b["true_lat"], b["true_lon"]))
            for a, b in itertools.pairwise(steps)
        ]
    )
    leg = config.speed_mps * config.step_s
    assert np.all(hops <= leg + 1e-3) and np.median(hops) == pytest.approx(leg, rel=1e-3)


def test_mission_writes_config_and_a_valid_png(mission, terrain_map: MapPackage) -> None:
    config, _, run_dir = mission
    saved = json.loads((run_dir / "config.json").read_text())
    assert saved["mission"]["start_lat"] == config.start_lat
    assert saved["mission"]["target_lon"] == config.target_lon
    assert Path(saved["map"]) == terrain_map.path
    png = (run_dir / "trajectory.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None and min(image.shape[:2]) > 200


@pytest.mark.parametrize("which", ["start", "target"])
def test_mission_outside_the_map_is_refused(
    which: str, terrain_map: MapPackage, terrain_raster: GeoRaster, camera: Camera, tmp_path: Path
) -> None:
    inside, _ = _diagonal(terrain_map, 0.3, 0.7)
    outside = (inside[0] + 0.5, inside[1])  # ~55 km north of a 1 km map
    points = (outside, inside) if which == "start" else (inside, outside)
    config = MissionConfig(*points[0], *points[1])
    with pytest.raises(OrthonavError, match=f"mission {which} .* outside the map"):
        run_mission(terrain_map, terrain_raster, camera, config, tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "steps.jsonl").exists()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("speed_mps", -5.0),
        ("speed_mps", 0.0),
        ("step_s", math.nan),
        ("max_time_s", -1.0),
        ("arrival_radius_m", math.inf),
    ],
)
def test_mission_config_rejects_impossible_numbers(field: str, value: float) -> None:
    with pytest.raises(OrthonavError, match=field):
        MissionConfig(50.0, 30.0, 50.01, 30.01, **{field: value})


@pytest.mark.parametrize(("lat", "lon"), [(91.0, 30.0), (50.0, 181.0), (math.nan, 30.0)])
def test_mission_config_rejects_impossible_positions(lat: float, lon: float) -> None:
    with pytest.raises(OrthonavError, match="mission start"):
        MissionConfig(lat, lon, 50.0, 30.0)


def test_mission_altitude_defaults_to_the_map_nominal(mission) -> None:
    """Without alt_agl_m the vehicle flies at the map's nominal altitude (+- the 5 % jitter)."""
    _, _, run_dir = mission
    alts = [json.loads(line)["true_alt_m"] for line in (run_dir / "steps.jsonl").read_text().splitlines()]
    assert all(abs(a / TERRAIN_ALT_M - 1.0) <= 0.05 + 1e-9 for a in alts)


def test_mission_bar_ends_full_with_the_reason(
    terrain_map: MapPackage, terrain_raster: GeoRaster, camera: Camera, tmp_path: Path, capsys
) -> None:
    """The bar is sized by the expected flight and ends at 100 % with why the mission ended,
    never stuck at a few per cent of the time limit as if it had aborted."""
    start, target = _diagonal(terrain_map, 0.4, 0.6)
    config = MissionConfig(*start, *target, speed_mps=20.0, step_s=5.0, arrival_radius_m=40.0, seed=4)
    run_mission(terrain_map, terrain_raster, camera, config, tmp_path / "run", progress=True)
    last = capsys.readouterr().err.strip().split("\r")[-1]
    assert "100%" in last and "arrived" in last, last
