"""Frames and priors the localizer must refuse: rejected with a reason, or a clear OrthonavError."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from conftest import NAIP_ALT_M, TERRAIN_ALT_M, random_pose

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, load_frame, render_frame
from orthonav.geo import GeoRaster, destination, distance_m
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage
from orthonav.types import Prior

MAPS = ["terrain_map", "naip_map"]


def _priors(package: MapPackage) -> list[Prior]:
    """No prior, and a full prior at the map centre."""
    lat, lon = package.grid.center_latlon
    alt = package.tiling.nominal_alt_m
    return [Prior(), Prior(lat, lon, alt, 30.0, 0.0, 0.0)]


@pytest.mark.parametrize("map_name", MAPS)
def test_uniform_frame_is_rejected_with_a_reason(
    request: pytest.FixtureRequest, camera: Camera, map_name: str
) -> None:
    package = request.getfixturevalue(map_name)
    localizer = Localizer(package, camera)
    frame = np.full((camera.height, camera.width, 3), 128, np.uint8)
    for prior in _priors(package):
        fix = localizer.localize(frame, prior)
        assert not fix.accepted
        assert "features" in fix.reason and "uniform" in fix.reason
        assert fix.pose is None and fix.covariance_enu_m2 is None


@pytest.mark.parametrize("map_name", MAPS)
def test_noise_frame_is_rejected_with_a_reason(
    request: pytest.FixtureRequest, camera: Camera, map_name: str
) -> None:
    """Pure noise has plenty of keypoints, but nothing on the map agrees with them."""
    package = request.getfixturevalue(map_name)
    localizer = Localizer(package, camera)
    rng = np.random.default_rng(0)
    for prior in _priors(package):
        frame = rng.integers(0, 256, (camera.height, camera.width, 3), dtype=np.uint8)
        fix = localizer.localize(frame, prior)
        assert not fix.accepted
        assert fix.reason
        assert fix.quality["keypoints"] > 100  # rejected for not matching, not for lack of features


def test_frame_from_another_place_is_never_accepted(
    naip_map: MapPackage, terrain_raster: GeoRaster, camera: Camera
) -> None:
    """Synthetic-terrain frames matched against the NAIP map: there is no right answer, so no fix."""
    rng = np.random.default_rng(8)
    localizer = Localizer(naip_map, camera)
    lat, lon = naip_map.grid.center_latlon
    accepted = []
    for _ in range(6):
        pose = random_pose(rng, terrain_raster, camera, TERRAIN_ALT_M)
        frame = render_frame(terrain_raster, camera, pose, Photometric.random(rng), rng)
        for prior in (Prior(), Prior(lat, lon, NAIP_ALT_M, pose.yaw_deg, 0.0, 0.0, sigma_m=1000.0)):
            fix = localizer.localize(frame, prior)
            assert fix.reason or fix.accepted
            if fix.accepted:
                accepted.append((fix.pose.lat, fix.pose.lon))
    assert accepted == []


@pytest.mark.parametrize("shape", [(240, 320, 3), (640, 480, 3), (480, 641)])
def test_wrong_size_frame_raises_naming_both_sizes(terrain_map: MapPackage, camera: Camera, shape) -> None:
    frame = np.zeros(shape, np.uint8)
    with pytest.raises(OrthonavError) as info:
        Localizer(terrain_map, camera).localize(frame)
    message = str(info.value)
    assert f"{shape[1]}x{shape[0]}" in message and f"{camera.width}x{camera.height}" in message


@pytest.mark.parametrize(
    "frame",
    [np.zeros((480, 640, 3), np.float32), np.zeros((480, 640, 3, 1), np.uint8), [[0, 1], [2, 3]]],
    ids=["float", "4-d", "list"],
)
def test_frame_of_wrong_type_raises(terrain_map: MapPackage, camera: Camera, frame) -> None:
    with pytest.raises(OrthonavError, match="uint8"):
        Localizer(terrain_map, camera).localize(frame)


def test_prior_outside_the_map_raises(terrain_map: MapPackage, camera: Camera) -> None:
    lat, lon = terrain_map.grid.center_latlon
    far = destination(lat, lon, 45.0, 20_000.0)  # 20 km away from a 1 km map
    frame = np.full((camera.height, camera.width, 3), 128, np.uint8)
    with pytest.raises(OrthonavError, match="outside the map"):
        Localizer(terrain_map, camera).localize(frame, Prior(*far, sigma_m=100.0))


def test_prior_just_off_the_map_within_its_uncertainty_is_accepted(
    terrain_map: MapPackage, camera: Camera
) -> None:
    """A prior 150 m past the edge with sigma 200 m may still see the map: no error is raised."""
    col, row = terrain_map.grid.width + 150.0 / terrain_map.gsd_m, terrain_map.grid.height / 2
    lat, lon = terrain_map.grid.pixel_to_latlon(col, row)
    assert float(distance_m(lat, lon, *terrain_map.grid.pixel_to_latlon(terrain_map.grid.width, row))) > 100
    frame = np.full((camera.height, camera.width, 3), 128, np.uint8)
    fix = Localizer(terrain_map, camera).localize(frame, Prior(float(lat), float(lon), sigma_m=200.0))
    assert not fix.accepted  # a blank frame, but no exception


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"lat": math.nan, "lon": 30.0}, "finite"),
        ({"lat": 50.0, "lon": math.inf}, "finite"),
        ({"lat": 95.0, "lon": 30.0}, "latitude 95"),
        ({"lat": -90.5, "lon": 30.0}, "latitude"),
        ({"lat": 50.0, "lon": 181.0}, "longitude 181"),
        ({"lat": 50.0}, "both latitude and longitude"),
        ({"alt_agl_m": math.nan}, "altitude"),
        ({"alt_agl_m": math.inf}, "altitude"),
        ({"alt_agl_m": -10.0}, "altitude"),
        ({"alt_agl_m": 0.0}, "altitude"),
        ({"alt_agl_m": 50_000.0}, "altitude"),
        ({"heading_deg": math.nan}, "heading"),
        ({"heading_deg": math.inf}, "heading"),
        ({"heading_deg": -math.inf}, "heading"),
        ({"heading_deg": 400.0}, "heading: expected an angle in -360..360"),
        ({"pitch_deg": 5.0}, "pitch and roll"),
        ({"pitch_deg": math.nan, "roll_deg": 0.0}, "pitch/roll"),
        ({"pitch_deg": 0.0, "roll_deg": 75.0}, "pitch/roll"),
        ({"sigma_m": 0.0}, "sigma_m"),
        ({"sigma_m": math.nan}, "sigma_m"),
        ({"heading_sigma_deg": -1.0}, "heading_sigma_deg"),
        ({"attitude_sigma_deg": math.nan}, "attitude_sigma_deg"),
        ({"attitude_sigma_deg": 112.0}, "attitude sigma 112.0 deg: expected at most 20 deg"),
    ],
)
def test_impossible_prior_raises(kwargs: dict, match: str) -> None:
    with pytest.raises(OrthonavError, match=match):
        Prior(**kwargs)


def test_load_frame_of_a_missing_file_raises(tmp_path: Path) -> None:
    with pytest.raises(OrthonavError, match="no such frame file"):
        load_frame(tmp_path / "nope.jpg")


@pytest.mark.parametrize(
    "content", [b"\xff\xd8 this is not really a jpeg" * 10, b""], ids=["garbage", "empty"]
)
def test_load_frame_of_a_non_image_raises(tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "frame.jpg"
    path.write_bytes(content)
    with pytest.raises(OrthonavError, match="cannot be decoded"):
        load_frame(path)


def test_load_frame_of_a_directory_raises(tmp_path: Path) -> None:
    (tmp_path / "frame.png").mkdir()
    with pytest.raises(OrthonavError, match="no such frame file"):
        load_frame(tmp_path / "frame.png")


@pytest.mark.parametrize(
    ("value", "limit", "decimals", "shown"),
    [(2.04, 2.0, 1, "2.04"), (2.6, 2.0, 1, "2.6"), (0.299, 0.3, 2, "0.299"), (25.4, 25.0, 0, "25.4")],
)
def test_a_value_beyond_its_limit_never_prints_as_the_limit(
    value: float, limit: float, decimals: int, shown: str
) -> None:
    from orthonav.errors import beyond

    assert beyond(value, limit, decimals) == shown
    assert beyond(value, limit, decimals) != format(limit, f".{decimals}f")


def test_a_too_low_altitude_is_named_before_any_work(
    naip_map: MapPackage, camera: Camera, tmp_path: Path
) -> None:
    """The geometry is checked first: a map at 100 m over 5 m pixels, or a frame at 1 m, is
    refused for its altitude (with the altitude that would do), not for a lack of texture."""
    from orthonav.mapdb import TilingConfig, build_map

    with pytest.raises(OrthonavError, match=r"nominal altitude 100 m: .* fly at least \d+ m high"):
        build_map(naip_map.source_path, tmp_path / "low", camera, TilingConfig(100.0), "orb", {})
    assert not (tmp_path / "low").exists()
    frame = np.zeros((camera.height, camera.width, 3), np.uint8)
    lat, lon = naip_map.grid.pixel_to_latlon(naip_map.grid.width / 2, naip_map.grid.height / 2)
    fix = Localizer(naip_map, camera).localize(frame, Prior(float(lat), float(lon), alt_agl_m=1.0))
    assert not fix.accepted and fix.reason.startswith("prior altitude 1 m: a frame covers only")


def test_a_very_large_map_states_its_cost_and_asks(
    terrain_tif: Path, camera: Camera, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Above the limit, a build says its size, disk and time and waits for --yes."""
    from typer.testing import CliRunner

    from orthonav.cli.main import app
    from orthonav.mapdb import TilingConfig, build, build_map

    with pytest.raises(
        OrthonavError, match=r"tiles \(more than 3\), up to [\d.]+ GB .* about [\d.]+ h .* --yes"
    ):
        build_map(terrain_tif, tmp_path / "big", camera, TilingConfig(300.0), "orb", {}, max_tiles=3)
    assert not (tmp_path / "big").exists()
    monkeypatch.setattr(build, "LARGE_MAP_TILES", 3)
    args = ["map", "build", str(terrain_tif), "--out", str(tmp_path / "m"), "--max-keypoints", "200"]
    refused = CliRunner().invoke(app, args)
    assert isinstance(refused.exception, OrthonavError) and "--yes" in str(refused.exception)
    built = CliRunner().invoke(app, [*args, "--yes"])
    assert built.exit_code == 0, built.output
