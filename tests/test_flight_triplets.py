"""Triplets from a real flight: flight logs read by pymavlink, frames synced by time.

The flight is written here, independently of the code under test: a straight track over
the NAIP 2018 map, logged as MAVLink (.tlog) and DataFlash (.bin) records, and frames
rendered from the NAIP 2020 orthophoto at the true poses.
"""

from __future__ import annotations

import logging
import math
import re
import struct
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import naip_path
from helpers_flight import ALT_M, PITCH_DEG, ROLL_DEG, T0, Track, mavlink, write_bin, write_tlog
from typer.testing import CliRunner

from orthonav.camera import Camera
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.flightlog import FlightLog, read_flight_log
from orthonav.frames import ImageFrames, TruePose, VideoFrames, render_frame
from orthonav.frames.views import ViewGeometry
from orthonav.geo import GeoRaster, distance_m
from orthonav.models.dataset import TripletConfig, TripletSet
from orthonav.models.heatmap import gradient_magnitude, ncc_heatmap
from orthonav.replay.flight_triplets import flight_triplets

CAMERA = Camera.from_hfov(640, 480, 60.0)
LOG_SECONDS = 20.0
SPEED_MPS = 15.0
HEADING_DEG = 60.0
FIRST_FRAME_S = 12.0  # log time of the first frame, after T0
FRAMES = 5
CONFIG = TripletConfig(seconds_earlier=10.0)


# Through the middle of the NAIP quarter-quad.
TRACK = Track(47.02036, -99.15478, HEADING_DEG, SPEED_MPS, LOG_SECONDS / 2)


@dataclass(frozen=True)
class Flight:
    tlog: Path
    frames: Path  # folder of PNG frames, one a second from FIRST_FRAME_S
    ortho: Path  # the map (2018); frames come from 2020


@pytest.fixture(scope="module")
def tlog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tlog(tmp_path_factory.mktemp("log") / "flight.tlog", TRACK)


@pytest.fixture(scope="module")
def flight(tlog: Path, tmp_path_factory: pytest.TempPathFactory) -> Flight:
    ortho, frames_from = naip_path("20180716"), naip_path("20200831")
    folder = tmp_path_factory.mktemp("frames")
    with GeoRaster(frames_from) as raster:
        for i in range(FRAMES):
            lat, lon = TRACK.at(FIRST_FRAME_S + i)
            pose = TruePose(lat, lon, ALT_M, HEADING_DEG, PITCH_DEG, ROLL_DEG)
            cv2.imwrite(str(folder / f"frame_{i:03d}.png"), render_frame(raster, CAMERA, pose))
    return Flight(tlog, folder, ortho)


def folder_frames(folder: Path) -> ImageFrames:
    return ImageFrames(sorted(folder.glob("*.png")), 1.0)


def build(flight: Flight, log: Path | None = None, **kwargs) -> TripletSet:
    with GeoRaster(flight.ortho) as raster:
        return flight_triplets(
            kwargs.pop("frames", folder_frames(flight.frames)),
            read_flight_log(log or flight.tlog),
            raster,
            CAMERA,
            CONFIG,
            kwargs.pop("offset_s", T0 + FIRST_FRAME_S),
            **kwargs,
        )


def raises(fragment: str):
    """Expect an OrthonavError whose message holds ``fragment`` literally."""
    return pytest.raises(OrthonavError, match=re.escape(fragment))


# --- flight logs --------------------------------------------------------------------------


def test_tlog_reads_back_what_was_written(tlog: Path) -> None:
    log = read_flight_log(tlog)
    assert len(log.time_s) == 101 and len(log.attitude_time_s) == 201
    np.testing.assert_allclose(log.time_s - T0, np.arange(101) * 0.2, atol=2e-6)
    truth = np.array([TRACK.at(t) for t in log.time_s - T0])
    assert np.max(distance_m(log.lat, log.lon, truth[:, 0], truth[:, 1])) < 0.02
    np.testing.assert_allclose(log.alt_agl_m, ALT_M, atol=1e-3)
    np.testing.assert_allclose(log.heading_deg, HEADING_DEG, atol=1e-4)
    np.testing.assert_allclose([log.pitch_deg.mean(), log.roll_deg.mean()], [PITCH_DEG, ROLL_DEG], atol=1e-4)
    assert log.span_s == pytest.approx((T0 + 0.05, T0 + LOG_SECONDS))


def test_tlog_keeps_to_the_first_vehicle(tlog: Path, tmp_path: Path) -> None:
    """A second system (another vehicle, a GCS relaying) in the same .tlog is left out."""
    path = tmp_path / "two.tlog"
    other = mavlink.MAVLink(None, srcSystem=2, srcComponent=1)
    stray = [
        mavlink.MAVLink_global_position_int_message(0, 10 * 10**7, 20 * 10**7, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_attitude_message(0, 0.5, 0.5, 3.0, 0, 0, 0),
    ]
    records = b"".join(struct.pack(">Q", round((T0 + 5.01) * 1e6)) + m.pack(other) for m in stray)
    path.write_bytes(tlog.read_bytes() + records)
    log, clean = read_flight_log(path), read_flight_log(tlog)
    np.testing.assert_array_equal(log.lat, clean.lat)
    np.testing.assert_array_equal(log.heading_deg, clean.heading_deg)


def test_poses_between_records_are_on_the_track(tlog: Path) -> None:
    log = read_flight_log(tlog)
    times = T0 + np.array([0.05, 3.33, 10.0, 17.91])  # between records and on one
    poses = log.at(times)
    truth = np.array([TRACK.at(t) for t in times - T0])
    assert np.max(distance_m(poses.lat, poses.lon, truth[:, 0], truth[:, 1])) < 0.02
    np.testing.assert_allclose(poses.heading_deg, HEADING_DEG, atol=1e-4)
    with raises("outside the log's"):
        log.at(np.array([T0 - 1.0]))


def test_heading_interpolates_across_north() -> None:
    times = np.array([0.0, 1.0, 2.0])
    log = FlightLog(
        Path("x.tlog"), times, np.full(3, 47.0), np.full(3, -99.0), np.full(3, 100.0),
        times, np.array([350.0, 10.0, 30.0]), np.zeros(3), np.zeros(3),
    )  # fmt: skip
    np.testing.assert_allclose(
        log.at(np.array([0.5, 0.75, 1.5])).heading_deg % 360, [0.0, 5.0, 20.0], atol=1e-9
    )


@pytest.mark.parametrize("home_alt", [True, False])
def test_dataflash_log(tmp_path: Path, home_alt: bool) -> None:
    log = read_flight_log(write_bin(tmp_path / "flight.bin", TRACK, home_alt))
    # GPS week and milliseconds give UNIX time; boot time is gone.
    np.testing.assert_allclose(log.time_s - T0, np.arange(21) * 0.5, atol=1e-3)
    truth = np.array([TRACK.at(t) for t in np.arange(21) * 0.5])
    assert np.max(distance_m(log.lat, log.lon, truth[:, 0], truth[:, 1])) < 0.02
    # POS.RelHomeAlt where logged (here +1 m to tell them apart), else GPS altitude above the first fix.
    expected = np.r_[0.0, np.full(20, ALT_M)] + (1.0 if home_alt else 0.0)
    np.testing.assert_allclose(log.alt_agl_m, expected, atol=1e-3)
    np.testing.assert_allclose(log.heading_deg, HEADING_DEG, atol=1e-4)


def test_log_without_gps(tmp_path: Path) -> None:
    path = write_tlog(tmp_path / "no_gps.tlog", TRACK, positions=False)
    with raises("no_gps.tlog: has no GPS positions (GLOBAL_POSITION_INT"):
        read_flight_log(path)


def test_log_with_one_position(tmp_path: Path) -> None:
    path = write_tlog(tmp_path / "short.tlog", TRACK, seconds=0.1)
    with raises("has only 1 GPS positions") as err:
        read_flight_log(path)
    assert "at least 2 are needed" in str(err.value)


@pytest.mark.parametrize(
    ("name", "content", "fragment"),
    [
        ("none.tlog", None, "no such flight log"),
        ("flight.csv", b"t,lat,lon\n", "expected an ArduPilot DataFlash log (.bin) or a MAVLink"),
        ("noise.bin", bytes(range(256)) * 8, "not an ArduPilot DataFlash log"),
        ("empty.bin", b"", "not an ArduPilot DataFlash log"),
        ("noise.tlog", bytes(range(256)) * 8, "has no GPS positions"),
    ],
)
def test_bad_log_files(tmp_path: Path, name: str, content: bytes | None, fragment: str) -> None:
    path = tmp_path / name
    if content is not None:
        path.write_bytes(content)
    with raises(fragment) as err:
        read_flight_log(path)
    assert name in str(err.value)


# --- triplets -----------------------------------------------------------------------------


def test_en_to_offset_inverts_offset_to_en() -> None:
    geometry = ViewGeometry(47.0, -99.0, 237.0, 5.0, (0.0, 0.0), (112, 84), (224, 168))
    for dx, dy in [(3.0, -7.5), (-20.0, 0.0), (0.0, 29.0)]:
        assert geometry.en_to_offset(*geometry.offset_to_en(dx, dy)) == pytest.approx((dx, dy))


def test_triplets_from_a_flight(flight: Flight) -> None:
    data = build(flight)
    assert len(data) == FRAMES and data.sources == [f"flight {flight.frames.name}"] * FRAMES
    assert data.anchors.shape[1:] == (84, 112, 3) and data.regions.shape[1:] == (168, 224, 3)
    # The temporal negative lies where the vehicle was 10 s earlier: behind it, i.e. straight
    # down in the heading-up view, speed x 10 s away.
    expected_px = SPEED_MPS * CONFIG.seconds_earlier / data.gsd_m
    np.testing.assert_allclose(data.temporal_px[:, 0], 0.0, atol=0.05)
    np.testing.assert_allclose(data.temporal_px[:, 1], expected_px, atol=0.05)
    # The anchor (2020 frame at the logged pose) sits at the centre of the 2018 region: the
    # gradient correlation peaks there and scores the temporal negative lower.
    assert np.all(np.abs(peak_shifts(data)) <= 1), peak_shifts(data)
    mx, my = data.margin_px
    for i in range(len(data)):
        heat = heatmap(data, i)
        tx, ty = np.round(data.temporal_px[i]).astype(int)
        assert heat[my, mx] > heat[my + ty, mx + tx] + 0.1


def heatmap(data: TripletSet, i: int) -> np.ndarray:
    """Gradient correlation of anchor ``i`` over its region; [my, mx] is the positive."""
    return ncc_heatmap(
        gradient_magnitude(data.regions[i]), gradient_magnitude(data.anchors[i]), data.anchor_masks[i]
    ).values


def peak_shifts(data: TripletSet) -> np.ndarray:
    """(N, 2) (dx, dy) px of each anchor's correlation peak from the positive."""
    mx, my = data.margin_px
    heats = [heatmap(data, i) for i in range(len(data))]
    peaks = [np.unravel_index(int(np.argmax(heat)), heat.shape) for heat in heats]
    return np.array([(col - mx, row - my) for row, col in peaks])


def test_a_sync_error_shows_along_the_track(flight: Flight) -> None:
    """Frames said to be 1 s later than they are: the logged position is 15 m (~3 px) ahead of
    the camera, so the frame's content sits that far back (down) in the heading-up region."""
    data = build(flight, offset_s=T0 + FIRST_FRAME_S + 1.0)
    expected = (0.0, SPEED_MPS * 1.0 / data.gsd_m)
    assert np.all(np.abs(peak_shifts(data) - expected) <= 1.0), peak_shifts(data)


def test_nadir_gimbal_ignores_the_vehicle_attitude(flight: Flight) -> None:
    """The frames were taken pitched 2 deg nose-up and rolled 1 deg left: taken as nadir, their
    content lies where the tilted camera looked, alt x tan(tilt) forward (up) and right."""
    data = build(flight, attitude=False)
    to_px = ALT_M / data.gsd_m
    expected = (-to_px * math.tan(math.radians(ROLL_DEG)), -to_px * math.tan(math.radians(PITCH_DEG)))
    assert np.all(np.abs(peak_shifts(data) - expected) <= 1.0), (peak_shifts(data), expected)


def test_every_other_frame_and_a_video(flight: Flight, tmp_path: Path) -> None:
    video = tmp_path / "flight.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 1.0, (CAMERA.width, CAMERA.height))
    if not writer.isOpened():
        pytest.skip("OpenCV here cannot write MJPG AVI videos")
    for path in sorted(flight.frames.glob("*.png")):
        writer.write(cv2.imread(str(path)))
    writer.release()
    from_folder = build(flight, every=2)
    from_video = build(flight, frames=VideoFrames(video), every=2)
    assert len(from_folder) == len(from_video) == 3  # frames 0, 2, 4
    np.testing.assert_allclose(from_video.temporal_px, from_folder.temporal_px)
    np.testing.assert_array_equal(from_video.regions, from_folder.regions)
    # JPEG compression aside, the same anchors.
    assert np.abs(from_video.anchors.astype(int) - from_folder.anchors).mean() < 3.0


def test_frames_off_the_map_are_skipped_and_counted(
    flight: Flight, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # From 14.5 s the log says 3 km up: a search region larger than the map, so frames 3 and 4 go.
    log = write_tlog(tmp_path / "climb.tlog", TRACK, alt_m=lambda t: ALT_M if t < 14.5 else 3000.0)
    with caplog.at_level(logging.WARNING):
        data = build(flight, log)
    assert len(data) == 3
    assert (
        "2 of 5 frames skipped, e.g. frame_003.png" in caplog.text
        and "beyond the edge of the map" in caplog.text
    )


def test_every_frame_off_the_map(flight: Flight, tmp_path: Path) -> None:
    log = write_tlog(tmp_path / "high.tlog", TRACK, alt_m=lambda t: 3000.0)
    with raises("no frame in the log's time span makes a sample; e.g. frame_000.png"):
        build(flight, log)


def test_times_that_do_not_overlap(flight: Flight) -> None:
    with raises("the log covers 1700000000.05..1700000020.00 s, the frames 0.00..4.00 s"):
        build(flight, offset_s=0.0)
    # Inside the log, but without 10 s of log before any frame for the temporal negative.
    with raises("needs 10 s of log before it"):
        build(flight, offset_s=T0 + 2.0)


def test_an_undecodable_frame_is_skipped_with_its_reason(
    flight: Flight, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """One bad frame of a flight is left out, said, and the others still make samples."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for path in sorted(flight.frames.glob("*.png")):
        (folder / path.name).write_bytes(path.read_bytes())
    (folder / "frame_002.png").write_bytes(b"not a png")
    with caplog.at_level(logging.WARNING):
        data = build(flight, frames=folder_frames(folder))
    assert len(data) == len(build(flight)) - 1
    assert "1 of 5 frames skipped, e.g. " in caplog.text and "frame_002.png: cannot be decoded" in caplog.text


def test_frames_of_another_camera(flight: Flight) -> None:
    with GeoRaster(flight.ortho) as raster, raises("but the camera is 800x600"):
        flight_triplets(
            folder_frames(flight.frames),
            read_flight_log(flight.tlog),
            raster,
            Camera.from_hfov(800, 600, 60.0),
            CONFIG,
            T0 + FIRST_FRAME_S,
        )


def test_bad_videos(tmp_path: Path) -> None:
    with raises("none.mp4: no such video file"):
        VideoFrames(tmp_path / "none.mp4")
    fake = tmp_path / "fake.mp4"
    fake.write_text("not a video")
    with raises("fake.mp4: cannot be opened as a video"):
        VideoFrames(fake)


def test_bad_frame_options(tmp_path: Path) -> None:
    with raises("interval: expected seconds > 0"):
        ImageFrames([tmp_path / "a.png"], 0.0)
    with raises("no image files"):
        ImageFrames([], 1.0)


# --- CLI ----------------------------------------------------------------------------------


@pytest.fixture()
def train_args(tmp_path: Path) -> list[str]:
    """``correction train`` up to the flight options; the dates' files only need to exist by name."""
    data = tmp_path / "dates"
    data.mkdir()
    for date in ("2018", "2020"):
        (data / f"ortho_{date}.tif").write_bytes(b"")
    return [
        "correction",
        "train",
        "--data",
        str(data),
        "--train-dates",
        "2018,2020",
        "--out",
        str(tmp_path / "run"),
    ]


def run_train(train_args: list[str], *flight_args: str | Path):
    return CliRunner().invoke(app, [*train_args, *(str(a) for a in flight_args)])


def expect_error(result, *fragments: str) -> None:
    assert isinstance(result.exception, OrthonavError), (result.exception, result.output)
    for fragment in fragments:
        assert fragment in str(result.exception)


def test_cli_flight_options_go_together(train_args: list[str], tmp_path: Path) -> None:
    log = write_tlog(tmp_path / "f.tlog", TRACK)
    expect_error(
        run_train(train_args, "--flight-frames", tmp_path, "--flight-offset", "0"),
        "--flight-log, --flight-map: missing",
        "go together",
    )
    expect_error(run_train(train_args, "--flight-log", log), "--flight-frames, --flight-map: missing")
    expect_error(
        run_train(train_args, "--flight-offset", "12"), "--flight-offset/--flight-interval: given without"
    )
    three = ["--flight-frames", tmp_path, "--flight-log", log, "--flight-map", tmp_path / "map.tif"]
    expect_error(run_train(train_args, *three), "--flight-offset: missing")
    expect_error(
        run_train(train_args, *three, "--flight-offset", "0"), "--flight-interval: missing", "image folder"
    )
    video = tmp_path / "f.avi"
    video.write_bytes(b"")
    three[1] = video
    expect_error(
        run_train(train_args, *three, "--flight-offset", "0", "--flight-interval", "1"),
        "--flight-interval: ",
        "is a video",
    )
    three[1] = tmp_path / "missing"
    expect_error(run_train(train_args, *three, "--flight-offset", "0"), "no such video file or image folder")


def test_cli_reaches_the_flight(train_args: list[str], flight: Flight) -> None:
    """Every option arrives: a wrong time offset gets the flight's own error, before any training."""
    result = run_train(
        train_args,
        "--flight-frames", flight.frames,
        "--flight-log", flight.tlog,
        "--flight-map", flight.ortho,
        "--flight-offset", "0",
        "--flight-interval", "1",
    )  # fmt: skip
    expect_error(result, "the log covers", "the frames 0.00..4.00 s")
