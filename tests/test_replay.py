"""Flight-log replay on the real NAIP map: a logged flight, its frames, fixes scored against the log.

The flight is written here with pymavlink (tests/helpers_flight.py), independently of the code
under test: a straight track at 1000 m over the NAIP 2018 orthophoto (a 480 x 420 px crop
around the track, the map), logged as a .tlog, and frames rendered from the NAIP 2020
orthophoto at the logged poses. Cross-year frames need a learned backend (ORB and SIFT fix
almost none across these years, see the README); ALIKED + LightGlue on one torch thread.
The inputs that go wrong use an ORB map of the same crop: they never need a fix.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import typer
from conftest import CAMERA, NAIP_ALT_M, SHARED_DATA, damage_video_frame, naip_path, write_naip_crop
from helpers_flight import PITCH_DEG, ROLL_DEG, T0, Track, write_tlog
from typer.testing import CliRunner

from orthonav.camera import Camera
from orthonav.cli.replay import replay
from orthonav.errors import OrthonavError
from orthonav.features import available_backends
from orthonav.flightlog.photos import read_photos
from orthonav.frames import FrameSource, ImageFrames, TruePose, VideoFrames, render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.replay import ReplayConfig, ReplayResult, camera_for_photos, replay_flight, replay_photos

TRACK = Track(47.02036, -99.15478, heading_deg=60.0, speed_mps=20.0, mid_s=25.0)
LOG_S = 50.0
FIRST_S, INTERVAL_S, FRAMES = 4.0, 6.0, 8  # frames at 4, 10, ... 46 s of the log
MAP_W, MAP_H = 480, 420  # px of 5 m: the track and every footprint along it, with a margin
# Frames are rendered at the logged pose with the logged attitude, so what remains is matching
# error and the 2018/2020 co-registration (about 1 m): 2 map pixels is the localizer's
# benchmark criterion for a correct fix, and what a replay must keep to on most frames.
MEDIAN_ERROR_M = 10.0
MAX_ERROR_M = 15.0
MIN_FIX_RATE = 0.75  # measured: 8 of 8, median 1.7 m, max 2.9 m


def frame_time(i: int, spacing_s: float = INTERVAL_S) -> float:
    return FIRST_S + i * spacing_s


def render(raster: GeoRaster, t: float) -> np.ndarray:
    lat, lon = TRACK.at(t)
    return render_frame(
        raster, CAMERA, TruePose(lat, lon, NAIP_ALT_M, TRACK.heading_deg, PITCH_DEG, ROLL_DEG)
    )


@pytest.fixture(scope="module")
def map_tif(tmp_path_factory: pytest.TempPathFactory) -> Path:
    with GeoRaster(naip_path("20180716")) as raster:
        col, row = (float(v) for v in raster.latlon_to_pixel(TRACK.lat0, TRACK.lon0))
    window = (round(col - MAP_W / 2), round(row - MAP_H / 2), MAP_W, MAP_H)
    return write_naip_crop("20180716", window, tmp_path_factory.mktemp("crop") / "naip2018.tif")


def build(map_tif: Path, out: Path, backend: str) -> MapPackage:
    return build_map(map_tif, out, CAMERA, TilingConfig(nominal_alt_m=NAIP_ALT_M), backend, progress=False)


@pytest.fixture(scope="module")
def orb_map(map_tif: Path, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    return build(map_tif, tmp_path_factory.mktemp("orb") / "map", "orb")


@pytest.fixture(scope="module")
def aliked_map(map_tif: Path, tmp_path_factory: pytest.TempPathFactory, torch_one_thread: None) -> MapPackage:
    if "aliked" not in available_backends():
        pytest.skip("cross-year replay needs the 'learned' extra (ALIKED + LightGlue)")
    return build(map_tif, tmp_path_factory.mktemp("aliked") / "map", "aliked")


@pytest.fixture(scope="module")
def tlog(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("log") / "flight.tlog"
    return write_tlog(path, TRACK, alt_m=lambda t: NAIP_ALT_M, seconds=LOG_S)


@pytest.fixture(scope="module")
def frames_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("frames")
    with GeoRaster(naip_path("20200831")) as raster:
        for i in range(FRAMES):
            cv2.imwrite(str(folder / f"frame_{i:03d}.png"), render(raster, frame_time(i)))
    return folder


def folder_frames(folder: Path) -> ImageFrames:
    return ImageFrames(sorted(folder.glob("*.png")), INTERVAL_S)


def run(
    tlog: Path, package: MapPackage, out: Path, frames: FrameSource, offset_s: float = T0 + FIRST_S, **config
) -> ReplayResult:
    """Replay with the test camera; ``config``: ReplayConfig fields."""
    return replay_flight(tlog, frames, offset_s, Localizer(package, CAMERA), out, ReplayConfig(**config))


def raises(fragment: str):
    return pytest.raises(OrthonavError, match=re.escape(fragment))


# --- accuracy ---------------------------------------------------------------------------------


def test_replay_follows_the_logged_track(
    tlog: Path, frames_dir: Path, aliked_map: MapPackage, tmp_path: Path
) -> None:
    result = run(tlog, aliked_map, tmp_path / "out", folder_frames(frames_dir), prior_sigma_m=50.0)
    summary = result.summary
    print(f"\nreplay NAIP 2020 frames on the 2018 map (aliked): {summary}")
    assert summary["frames"] == FRAMES and summary["skipped"] == {"outside the log": 0, "off the map": 0}
    assert summary["fix_rate"] >= MIN_FIX_RATE
    assert summary["error_m"]["median"] < MEDIAN_ERROR_M and summary["error_m"]["max"] < MAX_ERROR_M
    # Each frame got the log at its own time: the track this test wrote, not another frame's place.
    times = np.array([r["time_s"] for r in result.records])
    np.testing.assert_allclose(times - T0, [frame_time(i) for i in range(FRAMES)], atol=1e-6)
    truth = np.array([TRACK.at(t) for t in times - T0])
    logged = np.array([(r["log_lat"], r["log_lon"]) for r in result.records])
    assert np.max(distance_m(logged[:, 0], logged[:, 1], truth[:, 0], truth[:, 1])) < 0.05
    for r in result.records:
        assert (r["log_alt_agl_m"], r["log_heading_deg"]) == pytest.approx((NAIP_ALT_M, TRACK.heading_deg))
        if r["fix"]["accepted"]:  # error_m is the distance from the logged position to the fix
            expected = distance_m(r["log_lat"], r["log_lon"], r["fix"]["lat"], r["fix"]["lon"])
            assert r["error_m"] == pytest.approx(float(expected), abs=1e-3)
    check_outputs(result.out_dir, result.records, summary)


def check_outputs(out: Path, records: list[dict], summary: dict) -> None:
    lines = (out / "replay.jsonl").read_text().splitlines()
    assert [json.loads(line) for line in lines] == records
    assert json.loads((out / "summary.json").read_text()) == summary
    assert (out / "replay.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    config = json.loads((out / "config.json").read_text())
    assert config["source"]["offset_s"] == T0 + FIRST_S and config["camera"]["width"] == CAMERA.width


def test_replay_without_a_position_prior(
    tlog: Path, frames_dir: Path, aliked_map: MapPackage, tmp_path: Path
) -> None:
    """Every tile searched, heading and attitude from the log: the same fixes, frames 0 and 4."""
    result = run(tlog, aliked_map, tmp_path / "out", folder_frames(frames_dir), prior_sigma_m=None, every=4)
    assert [r["frame"] for r in result.records] == ["frame_000.png", "frame_004.png"]
    assert result.summary["fixes"] >= 1 and result.summary["error_m"]["max"] < MAX_ERROR_M
    assert json.loads((tmp_path / "out" / "config.json").read_text())["replay"]["prior_sigma_m"] is None


# --- inputs that go wrong ----------------------------------------------------------------------


def test_frames_outside_the_log_are_skipped_and_counted(
    tlog: Path, frames_dir: Path, orb_map: MapPackage, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Said to start at 30 s, the frames run to 72 s: the 4 after the log's end at 50 s are left out."""
    with caplog.at_level(logging.WARNING):
        result = run(tlog, orb_map, tmp_path / "out", folder_frames(frames_dir), offset_s=T0 + 30.0)
    assert [r["frame"] for r in result.records] == [f"frame_{i:03d}.png" for i in range(4)]
    assert result.summary["skipped"]["outside the log"] == 4
    assert "4 of 8 frames lie outside the log flight.tlog" in caplog.text


def test_no_frame_in_the_log(tlog: Path, frames_dir: Path, orb_map: MapPackage, tmp_path: Path) -> None:
    with raises(
        "no frame falls in the flight log flight.tlog: the log covers 1700000000.05..1700000050.00 s"
    ):
        run(tlog, orb_map, tmp_path / "out", folder_frames(frames_dir), offset_s=0.0)
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def short_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 frames 2 s apart from 4 s: 8 s of a 50 s flight."""
    path = tmp_path_factory.mktemp("video") / "short.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 0.5, (CAMERA.width, CAMERA.height))
    if not writer.isOpened():
        pytest.skip("OpenCV here cannot write MJPG AVI videos")
    with GeoRaster(naip_path("20200831")) as raster:
        for i in range(4):
            writer.write(render(raster, frame_time(i, 2.0)))
    writer.release()
    return path


def test_a_video_shorter_than_the_log(
    tlog: Path, short_video: Path, orb_map: MapPackage, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING):
        result = run(tlog, orb_map, tmp_path / "out", VideoFrames(short_video))
    assert result.summary["frames"] == 4
    assert (
        "short.avi: frames for 6.0 s of the 50.0 s logged in flight.tlog; none for 4.0 s at its start "
        "and 40.0 s at its end" in caplog.text
    )


def test_a_video_cut_short_ends_the_replay_early(
    tlog: Path, short_video: Path, orb_map: MapPackage, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A video truncated in the copy: its header announces 4 frames, it holds 2."""
    cut = tmp_path / "cut.avi"
    data = short_video.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    frames = VideoFrames(cut)
    assert frames.count == 4
    with caplog.at_level(logging.WARNING):
        result = run(tlog, orb_map, tmp_path / "out", frames)
    assert len(result.records) == result.summary["frames"] < 4
    assert result.summary["skipped"]["not in the frames"] == 4 - len(result.records)
    assert "the frames end early" in caplog.text
    assert len((tmp_path / "out" / "replay.jsonl").read_text().splitlines()) == len(result.records)


def test_a_damaged_frame_is_one_rejected_record_and_the_replay_goes_on(
    tlog: Path, short_video: Path, frames_dir: Path, orb_map: MapPackage, tmp_path: Path
) -> None:
    """A Motion JPEG frame with data zeroed (which FFmpeg would conceal) and a PNG cut short in a
    folder: each is a rejection saying why, and every frame around it is still localized (the
    ORB map of another year rejects most of them, for its own reasons)."""
    damaged = damage_video_frame(short_video, tmp_path / "damaged.avi", 1)
    video = run(tlog, orb_map, tmp_path / "video", VideoFrames(damaged)).records
    folder = tmp_path / "frames"
    folder.mkdir()
    for png in sorted(frames_dir.glob("*.png")):
        (folder / png.name).write_bytes(png.read_bytes())
    cut = folder / "frame_002.png"
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    images = run(tlog, orb_map, tmp_path / "folder", folder_frames(folder)).records
    assert (len(video), len(images)) == (4, FRAMES)
    for records, frame, words in ((video, 1, "damaged JPEG ("), (images, 2, "cannot be decoded")):
        reasons = [r["fix"]["reason"] for r in records]
        assert not records[frame]["fix"]["accepted"] and words in reasons[frame]
        assert not any(words in reason for reason in reasons[:frame] + reasons[frame + 1 :]), reasons


@pytest.mark.parametrize(
    ("name", "content", "fragment"),
    [
        ("noise.tlog", bytes(range(256)) * 8, "noise.tlog: has no GPS positions"),
        ("noise.bin", bytes(range(256)) * 8, "noise.bin: not an ArduPilot DataFlash log"),
        ("gpsless.tlog", None, "gpsless.tlog: has no GPS positions (GLOBAL_POSITION_INT"),
    ],
)
def test_corrupt_and_gps_less_logs(
    name: str, content: bytes | None, fragment: str, frames_dir: Path, orb_map: MapPackage, tmp_path: Path
) -> None:
    path = tmp_path / name
    if content is None:
        write_tlog(path, TRACK, positions=False, seconds=LOG_S)
    else:
        path.write_bytes(content)
    with raises(fragment):
        run(path, orb_map, tmp_path / "out", folder_frames(frames_dir))
    assert not (tmp_path / "out").exists()


def test_frames_of_another_camera(tlog: Path, frames_dir: Path, orb_map: MapPackage, tmp_path: Path) -> None:
    with raises("frame_000.png: 640x480 px, but the camera is 800x600"):
        localizer = Localizer(orb_map, Camera.from_hfov(800, 600, 60.0))
        replay_flight(tlog, folder_frames(frames_dir), T0 + FIRST_S, localizer, tmp_path / "out")


@pytest.fixture(scope="module")
def photos() -> Path:
    folder = SHARED_DATA / "brighton_beach" / "images"
    if not folder.is_dir():
        pytest.skip(f"real DJI photos not available: {folder} is missing")
    return folder


def test_photos_outside_the_map(photos: Path, orb_map: MapPackage, tmp_path: Path) -> None:
    flight = read_photos(photos)
    with raises("none of its 18 frames was taken over the map") as err:
        replay_photos(flight, Localizer(orb_map, camera_for_photos(flight, None)), tmp_path / "out")
    assert "46.8" in str(err.value) and "km from the map's centre" in str(err.value)


def test_bad_replay_options() -> None:
    with raises("prior sigma: expected metres > 0"):
        ReplayConfig(prior_sigma_m=0.0)


# --- CLI -----------------------------------------------------------------------------------------


def invoke(*args: str | Path | float):
    app = typer.Typer(pretty_exceptions_enable=False)
    app.command()(replay)
    return CliRunner().invoke(app, [str(a) for a in args])


def test_cli_writes_the_replay(tlog: Path, frames_dir: Path, orb_map: MapPackage, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = invoke(
        tlog, "--map", orb_map.path, "--frames", frames_dir, "--offset", T0 + FIRST_S,
        "--interval", INTERVAL_S, "--every", 2, "--prior-sigma", "none", "--features", "orb", "--out", out,
    )  # fmt: skip
    assert result.exit_code == 0, (result.exception, result.output)
    assert "frames localized: 4" in result.output
    for name in ("replay.jsonl", "summary.json", "config.json", "replay.png"):
        assert (out / name).is_file(), name
    config = json.loads((out / "config.json").read_text())
    assert config["replay"]["every"] == 2 and config["replay"]["prior_sigma_m"] is None
    assert config["source"]["interval_s"] == INTERVAL_S and config["features"] == "orb"
    assert len((out / "replay.jsonl").read_text().splitlines()) == 4


def expect_error(result, *fragments: str) -> None:
    assert isinstance(result.exception, OrthonavError), (result.exception, result.output)
    for fragment in fragments:
        assert fragment in str(result.exception)


def test_cli_input_errors(
    tlog: Path, frames_dir: Path, orb_map: MapPackage, photos: Path, tmp_path: Path
) -> None:
    common = ["--map", orb_map.path, "--out", tmp_path / "run"]
    expect_error(invoke(tlog, *common, "--frames", frames_dir), "needs --frames", "and --offset")
    expect_error(invoke(tlog, *common, "--frames", frames_dir, "--offset", 0), "--interval: missing")
    expect_error(
        invoke(
            tlog, *common, "--frames", frames_dir, "--offset", 0, "--interval", 6, "--prior-sigma", "wide"
        ),
        "--prior-sigma 'wide'",
    )
    expect_error(
        invoke(tlog, *common, "--frames", frames_dir, "--features", "sift"), "cannot be matched with 'sift'"
    )
    expect_error(invoke(photos, *common, "--offset", 0), "--offset: photos carry their own poses")
    camera = tmp_path / "camera.json"
    camera.write_text(json.dumps({"width": 800, "height": 600, "hfov_deg": 60}))
    expect_error(
        invoke(
            tlog,
            *common,
            "--frames",
            frames_dir,
            "--offset",
            T0 + FIRST_S,
            "--interval",
            6,
            "--camera",
            camera,
        ),
        "but the camera is 800x600",
    )


def test_cli_photos_over_another_map(photos: Path, orb_map: MapPackage, tmp_path: Path) -> None:
    """The photos' camera comes from their EXIF; Duluth is not on a North Dakota map."""
    result = invoke(photos, "--map", orb_map.path, "--out", tmp_path / "run")
    expect_error(result, "images: none of its 18 frames was taken over the map")
