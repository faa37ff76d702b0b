"""DJI photos read as a flight: EXIF GPS and time, XMP height and gimbal, intrinsics from EXIF.

On the 18 real photos of ../shared/data/brighton_beach (DJI Phantom 3, FC300S, Duluth MN,
2016-06-23, about 40 m above the take-off point, nadir gimbal). Expected values come from
the data's description and from physics (a multirotor mapping at a few m/s), not from the reader.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SHARED_DATA
from PIL import Image

from orthonav.errors import OrthonavError
from orthonav.flightlog.photos import SENSOR_WIDTH_MM, read_photo, read_photos
from orthonav.geo import distance_m

PHOTOS = SHARED_DATA / "brighton_beach" / "images"
FOCAL_MM = 3.61
WIDTH, HEIGHT = 4000, 2250


@pytest.fixture(scope="module")
def folder() -> Path:
    if not (PHOTOS / "DJI_0018.JPG").is_file():
        pytest.skip(f"real DJI photos not available: {PHOTOS} is missing")
    return PHOTOS


def raises(fragment: str):
    return pytest.raises(OrthonavError, match=re.escape(fragment))


def test_every_photo_is_read_in_time_order(folder: Path) -> None:
    flight = read_photos(folder)
    assert len(flight) == 18
    assert [p.path.name for p in flight.photos] == [f"DJI_00{n}.JPG" for n in range(18, 36)]
    times = np.array([p.time_s for p in flight.photos])
    assert np.all(np.diff(times) > 0)
    # 2016-06-23 16:31:59 (camera clock, no zone written: read as UTC) for the first photo.
    assert times[0] == 1466699519.0


def test_positions_heights_and_gimbal_are_plausible(folder: Path) -> None:
    flight = read_photos(folder)
    for photo in flight.photos:
        assert 46.84 < photo.lat < 46.85 and -92.00 < photo.lon < -91.99  # Duluth, MN
        assert photo.rel_alt_m == pytest.approx(40.0, abs=0.5)
        assert photo.gimbal_pitch_deg == pytest.approx(-89.9, abs=0.2)  # nadir
        assert photo.gimbal_roll_deg == pytest.approx(0.0, abs=1.0)
        assert photo.tilt_deg[0] == pytest.approx(0.1, abs=0.2)
        # GNSS altitude above sea level minus the height above take-off: one take-off point.
        assert photo.alt_amsl_m - photo.rel_alt_m == pytest.approx(158.5, abs=0.5)
        # The gimbal follows the aircraft's yaw on a Phantom 3.
        assert abs((photo.gimbal_yaw_deg - photo.flight_yaw_deg + 180) % 360 - 180) < 5.0
        assert photo.has_xmp


def test_consecutive_photos_move_as_a_mapping_drone_does(folder: Path) -> None:
    """7-9 s apart and 13-26 m apart: 1.5-3 m/s, the same along each leg of the pattern."""
    poses = read_photos(folder).poses()
    steps = distance_m(poses.lat[:-1], poses.lon[:-1], poses.lat[1:], poses.lon[1:])
    dt = np.diff(poses.time_s)
    speeds = steps / dt
    assert np.all((dt >= 6) & (dt <= 10)), dt
    assert np.all((speeds > 1.5) & (speeds < 3.0)), speeds
    legs = speeds[steps < 20.0]  # leave out the turns between legs
    assert len(legs) >= 14 and np.std(legs) < 0.1 * np.mean(legs)


def test_poses_and_interpolation_between_photos(folder: Path) -> None:
    flight = read_photos(folder)
    poses = flight.poses()
    np.testing.assert_allclose(poses.alt_agl_m, [p.rel_alt_m for p in flight.photos])
    np.testing.assert_allclose(poses.pitch_deg, [p.gimbal_pitch_deg + 90.0 for p in flight.photos])
    np.testing.assert_allclose(poses.heading_deg, [p.gimbal_yaw_deg % 360 for p in flight.photos])
    mid = flight.at(np.array([(poses.time_s[0] + poses.time_s[1]) / 2.0]))
    # Halfway in time, halfway in space (straight leg between the first two photos).
    half = float(distance_m(poses.lat[0], poses.lon[0], poses.lat[1], poses.lon[1])) / 2.0
    assert float(distance_m(poses.lat[0], poses.lon[0], mid.lat[0], mid.lon[0])) == pytest.approx(
        half, rel=0.01
    )


def test_intrinsics_from_the_focal_length_and_sensor_width(folder: Path) -> None:
    camera = read_photos(folder).camera
    assert camera is not None and (camera.width, camera.height) == (WIDTH, HEIGHT)
    expected_fx = FOCAL_MM / SENSOR_WIDTH_MM["FC300S"] * WIDTH
    assert camera.fx == pytest.approx(expected_fx) and camera.fy == camera.fx
    # The Phantom 3's lens: 94 deg diagonal on its 4:3 frame, so about 81 deg across.
    assert camera.hfov_deg == pytest.approx(2 * math.degrees(math.atan(2000 / 2331)), abs=1.0)
    assert (camera.cx, camera.cy) == (WIDTH / 2, HEIGHT / 2)


def small_copy(source: Path, out: Path, keep_exif: bool) -> Path:
    """A 400 x 225 copy: with its EXIF (Pillow writes no XMP unless asked) or without any metadata."""
    with Image.open(source) as image:
        exif = image.getexif()
        small = image.resize((400, 225))
    if keep_exif:
        small.save(out, exif=exif)
    else:
        cv2.imwrite(str(out), cv2.cvtColor(np.asarray(small), cv2.COLOR_RGB2BGR))
    return out


def test_photo_without_xmp_falls_back_to_exif(
    folder: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    small_copy(folder / "DJI_0018.JPG", tmp_path / "a.jpg", keep_exif=True)
    with caplog.at_level(logging.WARNING):
        flight = read_photos(tmp_path)
    photo, original = flight.photos[0], read_photo(folder / "DJI_0018.JPG")
    assert not photo.has_xmp and "1 of 1 photos have no DJI XMP (e.g. a.jpg)" in caplog.text
    assert (photo.lat, photo.lon, photo.alt_amsl_m, photo.time_s) == (
        original.lat,
        original.lon,
        original.alt_amsl_m,
        original.time_s,
    )
    assert photo.rel_alt_m is None and photo.heading_deg is None and photo.tilt_deg == (None, None)
    assert np.isnan(flight.poses().alt_agl_m[0])
    # Same lens, smaller image: the same field of view.
    assert photo.camera.hfov_deg == pytest.approx(original.camera.hfov_deg, abs=1e-6)


def test_photo_without_exif_is_a_clear_error(folder: Path, tmp_path: Path) -> None:
    small_copy(folder / "DJI_0020.JPG", tmp_path / "stripped.jpg", keep_exif=False)
    with raises("stripped.jpg: no EXIF GPS position (GPSLatitude/GPSLongitude)"):
        read_photos(tmp_path)


def test_photo_without_capture_time(folder: Path, tmp_path: Path) -> None:
    with Image.open(folder / "DJI_0021.JPG") as image:
        exif = image.getexif()
        exif.get_ifd(0x8769).pop(0x9003)  # DateTimeOriginal
        image.resize((400, 225)).save(tmp_path / "timeless.jpg", exif=exif)
    with raises("timeless.jpg: EXIF DateTimeOriginal missing"):
        read_photo(tmp_path / "timeless.jpg")


def test_one_photo_is_no_track_to_interpolate(folder: Path, tmp_path: Path) -> None:
    small_copy(folder / "DJI_0018.JPG", tmp_path / "a.jpg", keep_exif=True)
    flight = read_photos(tmp_path)
    assert len(flight.poses()) == 1
    with raises("a flight log needs at least 2 photos with distinct capture times"):
        flight.log()


def test_bad_photo_inputs(tmp_path: Path) -> None:
    with raises("no such photo folder"):
        read_photos(tmp_path / "none")
    with raises("no JPEG photos"):
        read_photos(tmp_path)
    (tmp_path / "broken.jpg").write_bytes(b"not a jpeg")
    with raises("broken.jpg: cannot be read as an image"):
        read_photos(tmp_path)
