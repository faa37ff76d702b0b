"""Camera frame sources: recorded (image folder, video) and live (video in real time, watched
folder, network stream, device), on frames cut from the real NAIP 2020 orthophoto.

Frames are told apart by content: frame ``i`` is a different window of the orthophoto, so a
source returning the wrong frame fails the pixel comparison, not only a count.
"""

from __future__ import annotations

import contextlib
import functools
import http.server
import logging
import os
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import SHARED_DATA, damage_video_frame, naip_path, png_declaring, zeroed_middle
from PIL import Image

from orthonav.errors import OrthonavError
from orthonav.frames import (
    FolderWatch,
    ImageFrames,
    Unreadable,
    VideoFrames,
    capture_time_from_name,
    frame_filename,
    list_images,
    load_frame,
    open_frames,
    open_live_source,
)
from orthonav.geo import GeoRaster, PixelWindow

WIDTH, HEIGHT = 320, 240
FRAMES = 12
FPS = 20.0
MJPG_MEAN_ERROR = 6.0  # grey levels: JPEG compression, far below the difference of two windows


@pytest.fixture(scope="module")
def crops() -> list[np.ndarray]:
    """FRAMES different 320 x 240 BGR windows of the NAIP 2020 orthophoto, 30 px apart."""
    with GeoRaster(naip_path("20200831")) as raster:
        return [
            cv2.cvtColor(raster.read_rgb(PixelWindow(100 + 30 * i, 200, WIDTH, HEIGHT)), cv2.COLOR_RGB2BGR)
            for i in range(FRAMES)
        ]


@pytest.fixture(scope="module")
def video(crops: list[np.ndarray], tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("video") / "flight.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (WIDTH, HEIGHT))
    if not writer.isOpened():
        pytest.skip("OpenCV here cannot write MJPG AVI videos")
    for crop in crops:
        writer.write(crop)
    writer.release()
    return path


def which_crop(image: np.ndarray, crops: list[np.ndarray]) -> int:
    """Index of the crop the image shows (JPEG-compressed or not), checked to be a close match."""
    errors = [np.abs(image.astype(int) - crop).mean() for crop in crops]
    best = int(np.argmin(errors))
    assert errors[best] < MJPG_MEAN_ERROR, errors
    return best


def raises(fragment: str):
    return pytest.raises(OrthonavError, match=re.escape(fragment))


# --- recorded frames ------------------------------------------------------------------------


def test_open_frames_tells_a_video_from_a_folder(
    video: Path, crops: list[np.ndarray], tmp_path: Path
) -> None:
    for i in (0, 1):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), crops[i])
    (tmp_path / "notes.txt").write_text("not a frame")
    folder = open_frames(tmp_path, 2.0)
    assert isinstance(folder, ImageFrames) and (folder.count, folder.interval_s) == (2, 2.0)
    assert [which_crop(image, crops) for _, image in folder.read([0, 1])] == [0, 1]
    clip = open_frames(video, None)
    assert isinstance(clip, VideoFrames) and clip.count == FRAMES
    assert clip.interval_s == pytest.approx(1.0 / FPS)
    assert [which_crop(image, crops) for _, image in clip.read([3, 7])] == [3, 7]


def test_open_frames_errors_name_the_options(video: Path, tmp_path: Path) -> None:
    with raises("--flight-interval: missing;"):
        open_frames(tmp_path, None, "--flight-frames", "--flight-interval")
    with raises("--interval: ") as err:
        open_frames(video, 1.0)
    assert "is a video: its frame rate sets the interval" in str(err.value)
    with raises("--frames ") as err:
        open_frames(tmp_path / "missing", 1.0)
    assert "no such video file or image folder" in str(err.value)
    with raises("no image files"):
        list_images(tmp_path)


# --- damaged frames ---------------------------------------------------------------------------

DRONE_PHOTO = SHARED_DATA / "brighton_beach" / "images" / "DJI_0018.JPG"


@pytest.fixture(scope="module")
def drone_jpeg() -> bytes:
    """A real 4000 x 2250 drone photo as the camera wrote it (restart markers, DJI's tables)."""
    if not DRONE_PHOTO.is_file():
        pytest.skip(f"../shared/data not present: {DRONE_PHOTO} is missing (real-data test)")
    return DRONE_PHOTO.read_bytes()


def test_damaged_jpegs_are_errors_in_libjpegs_words(drone_jpeg: bytes, tmp_path: Path) -> None:
    """Zeroed data and truncation, even with the end marker put back, are errors; OpenCV alone
    decodes the zeroed photo without a word (grey where data was lost)."""
    zeroed = zeroed_middle(drone_jpeg)
    assert cv2.imdecode(np.frombuffer(zeroed, np.uint8), cv2.IMREAD_COLOR) is not None
    cut = drone_jpeg[: len(drone_jpeg) * 2 // 3]
    damaged = {
        "zeroed.jpg": (zeroed, "Corrupt JPEG data"),
        "cut.jpg": (cut, "Premature end of JPEG file"),
        "cut_with_end.jpg": (cut + b"\xff\xd9", "Corrupt JPEG data"),
    }
    for name, (data, words) in damaged.items():
        (tmp_path / name).write_bytes(data)
        with raises(f"{tmp_path / name}: damaged JPEG (") as err:
            load_frame(tmp_path / name)
        assert words in str(err.value)
    np.testing.assert_array_equal(load_frame(DRONE_PHOTO), cv2.imread(str(DRONE_PHOTO)))


def test_a_jpeg_is_turned_upright_by_its_exif_orientation_as_opencv_does(
    crops: list[np.ndarray], tmp_path: Path
) -> None:
    path = tmp_path / "rotated.jpg"
    exif = Image.Exif()
    exif[0x0112] = 6  # the camera was turned 90 degrees clockwise
    Image.fromarray(crops[0][:, :, ::-1]).save(path, exif=exif, quality=95)
    image = load_frame(path)
    assert image.shape == (WIDTH, HEIGHT, 3)
    np.testing.assert_array_equal(image, cv2.imread(str(path)))


def test_an_image_over_opencvs_pixel_limit_is_a_clear_error(tmp_path: Path) -> None:
    """A PNG that declares 40000 x 40000 px: OpenCV raises cv2.error; the user reads why."""
    path = tmp_path / "huge.png"
    path.write_bytes(png_declaring(40000, 40000))
    with raises(f"{path}: cannot be decoded as an image (more than") as err:
        load_frame(path)
    assert "CV_IO_MAX_IMAGE_PIXELS" in str(err.value)


# --- names that carry capture times ---------------------------------------------------------


def test_frame_filename_carries_the_capture_time() -> None:
    name = frame_filename(1_700_000_000.123456)
    assert name == "frame_1700000000123456.jpg"
    assert capture_time_from_name(Path(name)) == pytest.approx(1_700_000_000.123456, abs=1e-6)
    assert frame_filename(12.5, ".png") == "frame_12500000.png"
    assert capture_time_from_name(Path("DJI_0018.JPG")) is None
    assert capture_time_from_name(Path("frame_12x.jpg")) is None


def test_a_damaged_video_frame_is_unreadable_with_its_reason_and_the_others_are_read(
    video: Path, crops: list[np.ndarray], tmp_path: Path
) -> None:
    """FFmpeg conceals the damage and OpenCV hands the frame over as good; a Motion JPEG frame
    is checked as a JPEG file is, and the frames after it are still read."""
    damaged = damage_video_frame(video, tmp_path / "damaged.avi", 5)
    capture = cv2.VideoCapture(str(damaged))
    decoded = [capture.read() for _ in range(FRAMES)]
    capture.release()
    assert all(ok for ok, _ in decoded)  # OpenCV alone: every frame, the damaged one too
    frames = list(VideoFrames(damaged).read(range(FRAMES)))
    assert [label for label, _ in frames] == [f"damaged.avi frame {i}" for i in range(FRAMES)]
    bad = frames[5][1]
    assert isinstance(bad, Unreadable) and bad.reason.startswith("damaged.avi frame 5: damaged JPEG (")
    good = [(i, image) for i, (_, image) in enumerate(frames) if i != 5]
    assert all(which_crop(image, crops) == i for i, image in good)


def test_images_of_a_folder_that_cannot_be_decoded_are_unreadable_not_the_end(
    crops: list[np.ndarray], tmp_path: Path
) -> None:
    files = [tmp_path / f"f{i}.jpg" for i in range(3)]
    for file, crop in zip(files, crops, strict=False):
        cv2.imwrite(str(file), crop)
    files[1].write_bytes(zeroed_middle(files[1].read_bytes(), 2000))
    frames = list(ImageFrames(files, 1.0).read(range(3)))
    assert isinstance(frames[1][1], Unreadable) and "damaged JPEG (Corrupt JPEG data" in frames[1][1].reason
    assert which_crop(frames[0][1], crops) == 0 and which_crop(frames[2][1], crops) == 2


# --- a video played in real time ------------------------------------------------------------


def test_video_plays_in_real_time(video: Path, crops: list[np.ndarray]) -> None:
    """Each grab returns the frame due at that moment, stamped start + index / fps; never one twice."""
    source = open_live_source(str(video), fps=FPS)
    try:
        first = source.grab(timeout_s=1.0)
        time.sleep(0.2)  # 4 frame periods: at least 4 frames are due, more on a slow machine
        later = source.grab(timeout_s=1.0)
    finally:
        source.close()
    assert first is not None and later is not None
    i, j = which_crop(first.image, crops), which_crop(later.image, crops)
    assert j >= i + 4
    assert first.label == f"flight.avi frame {i}" and later.label == f"flight.avi frame {j}"
    assert later.capture_time_s - first.capture_time_s == pytest.approx((j - i) / FPS, abs=1e-6)


def test_a_grab_before_the_next_frame_is_due_times_out(video: Path) -> None:
    source = open_live_source(str(video), fps=0.1)  # one frame every 10 s
    try:
        assert source.grab(timeout_s=1.0) is not None  # frame 0 is due at once
        assert source.grab(timeout_s=0.05) is None
    finally:
        source.close()


def test_a_video_that_ends_gives_nothing_more(video: Path, caplog: pytest.LogCaptureFixture) -> None:
    source = open_live_source(str(video), fps=200.0)  # 12 frames in 60 ms
    try:
        time.sleep(0.2)
        with caplog.at_level(logging.WARNING):
            assert source.grab(timeout_s=0.05) is None
            assert source.grab(timeout_s=0.05) is None
    finally:
        source.close()
    assert "flight.avi: the video ended after 12 frames" in caplog.text


def test_a_damaged_frame_of_a_video_played_live_is_passed_over_with_its_reason(
    video: Path, crops: list[np.ndarray], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    damaged = damage_video_frame(video, tmp_path / "damaged.avi", 0)
    source = open_live_source(str(damaged), fps=FPS)
    try:
        with caplog.at_level(logging.WARNING):
            assert source.grab(timeout_s=1.0) is None  # frame 0, due at once, is damaged
        later = source.grab(timeout_s=1.0)
    finally:
        source.close()
    assert "damaged.avi frame 0: damaged JPEG (" in caplog.text and "; skipped" in caplog.text
    assert later is not None and later.label != "damaged.avi frame 0"
    assert later.label == f"damaged.avi frame {which_crop(later.image, crops)}"


# --- a watched folder ------------------------------------------------------------------------


def jpeg(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".jpg", image)
    assert ok
    return data.tobytes()


def test_watched_folder_returns_only_new_images_newest_first(
    tmp_path: Path, crops: list[np.ndarray], caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / frame_filename(100.0)).write_bytes(jpeg(crops[0]))  # there before: never returned
    source = open_live_source(str(tmp_path))
    assert isinstance(source, FolderWatch)
    assert source.grab(timeout_s=0.1) is None
    for i, t in ((1, 101.0), (2, 102.0), (3, 103.0)):
        (tmp_path / frame_filename(t)).write_bytes(jpeg(crops[i]))
    frame = source.grab(timeout_s=1.0)
    assert frame is not None and which_crop(frame.image, crops) == 3
    assert frame.capture_time_s == pytest.approx(103.0) and frame.label == frame_filename(103.0)
    assert source.dropped == 2  # 101 and 102 came before 103 was read: stale, dropped
    assert source.grab(timeout_s=0.1) is None
    # A name without a capture time: the file's modification time.
    shot = tmp_path / "shot.png"
    cv2.imwrite(str(shot), crops[4])
    os.utime(shot, (104.5, 104.5))
    frame = source.grab(timeout_s=1.0)
    assert frame is not None and frame.capture_time_s == pytest.approx(104.5)
    assert which_crop(frame.image, crops) == 4
    assert "skipped" not in caplog.text


def test_partial_and_broken_files_are_skipped_with_a_warning(
    tmp_path: Path, crops: list[np.ndarray], caplog: pytest.LogCaptureFixture
) -> None:
    source = FolderWatch(tmp_path)
    whole = jpeg(crops[5])
    cut = tmp_path / frame_filename(206.0)
    (tmp_path / frame_filename(205.0)).write_bytes(jpeg(crops[4]))
    cut.write_bytes(whole[: len(whole) // 2])  # still being written
    (tmp_path / frame_filename(207.0, ".png")).write_bytes(b"not a png at all")
    (tmp_path / "notes.txt").write_text("not an image name: ignored")
    (tmp_path / ".frame_208000000.tmp.jpg").write_bytes(jpeg(crops[6]))  # a writer's temporary name
    with caplog.at_level(logging.WARNING):
        frame = source.grab(timeout_s=1.0)
    assert frame is not None and which_crop(frame.image, crops) == 4  # the newest readable one
    assert caplog.text.count("skipped until it changes") == 2
    for name in (cut.name, frame_filename(207.0, ".png")):
        assert f"{name}: partial (no end marker yet)" in caplog.text
    assert "notes.txt" not in caplog.text and ".tmp" not in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert source.grab(timeout_s=0.1) is None  # unchanged bad files: no second warning
    assert caplog.text == ""
    cut.write_bytes(whole)  # the writer finishes
    frame = source.grab(timeout_s=1.0)
    assert frame is not None and which_crop(frame.image, crops) == 5
    assert frame.capture_time_s == pytest.approx(206.0)


def test_a_damaged_jpeg_in_a_watched_folder_is_skipped_with_its_reason(
    tmp_path: Path, crops: list[np.ndarray], caplog: pytest.LogCaptureFixture
) -> None:
    """Zeroed data keeps the end marker that tells a finished file: libjpeg's warning tells it."""
    source = FolderWatch(tmp_path)
    (tmp_path / frame_filename(300.0)).write_bytes(jpeg(crops[2]))
    damaged = tmp_path / frame_filename(301.0)
    damaged.write_bytes(zeroed_middle(jpeg(crops[3])))
    with caplog.at_level(logging.WARNING):
        frame = source.grab(timeout_s=1.0)
    assert frame is not None and which_crop(frame.image, crops) == 2
    assert f"{damaged}: damaged JPEG (Corrupt JPEG data" in caplog.text


def test_a_watched_folder_is_listed_only_when_it_may_hold_something_new(
    tmp_path: Path, crops: list[np.ndarray], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A companion asks every few milliseconds and a camera's folder grows all flight: the
    folder is listed again only when its time changes, a skipped file changes, or ``rescan_s``
    passes (a file system whose times are coarse)."""
    for k in range(300):  # an hour's frames would be thousands
        (tmp_path / frame_filename(10.0 + k)).write_bytes(b"old")
    source = FolderWatch(tmp_path)
    listings = []
    real_scandir = os.scandir
    monkeypatch.setattr(os, "scandir", lambda path: listings.append(path) or real_scandir(path))
    assert source.grab(timeout_s=0.0) is None and len(listings) == 1
    for _ in range(20):
        assert source.grab(timeout_s=0.0) is None
    assert len(listings) == 1  # nothing changed: not listed again
    (tmp_path / frame_filename(400.0)).write_bytes(jpeg(crops[1]))
    frame = source.grab(timeout_s=1.0)
    assert frame is not None and which_crop(frame.image, crops) == 1 and len(listings) == 2
    # A folder time that does not move (coarse or restored): found at the next rescan.
    stamp = os.stat(tmp_path)
    (tmp_path / frame_filename(401.0)).write_bytes(jpeg(crops[2]))
    os.utime(tmp_path, ns=(stamp.st_atime_ns, stamp.st_mtime_ns))
    assert source.grab(timeout_s=0.0) is None and len(listings) == 2
    monkeypatch.setattr(source, "rescan_s", 0.0)
    frame = source.grab(timeout_s=1.0)
    assert frame is not None and which_crop(frame.image, crops) == 2


def test_watched_folder_can_take_what_is_already_there(tmp_path: Path, crops: list[np.ndarray]) -> None:
    cv2.imwrite(str(tmp_path / frame_filename(300.0, ".png")), crops[7])
    frame = open_live_source(str(tmp_path), existing=True).grab(timeout_s=0.5)
    assert frame is not None and which_crop(frame.image, crops) == 7


# --- a network stream -----------------------------------------------------------------------


@contextlib.contextmanager
def served(video: Path) -> Iterator[str]:
    """A video served over HTTP on the loopback interface: a network stream for OpenCV."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(
        ("127.0.0.1", 0), functools.partial(Quiet, directory=str(video.parent))
    )
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/{video.name}"
    finally:
        server.shutdown()
        thread.join()


@pytest.fixture()
def http_video(video: Path) -> Iterator[str]:
    with served(video) as url:
        yield url


def test_stream_frames_are_read_and_stamped_on_arrival(http_video: str, crops: list[np.ndarray]) -> None:
    before = time.time()
    source = open_live_source(http_video)
    try:
        frames = [source.grab(timeout_s=5.0) for _ in range(2)]
    finally:
        source.close()
    after = time.time()
    assert all(f is not None for f in frames)
    for frame in frames:
        which_crop(frame.image, crops)
        assert before <= frame.capture_time_s <= after
    assert frames[0].label != frames[1].label and frames[0].label.startswith(http_video + " #")


def test_a_damaged_frame_of_a_stream_is_passed_over_with_its_reason(
    video: Path, crops: list[np.ndarray], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Every frame the stream hands over is a whole one; the damaged one is said, not delivered."""
    damaged = damage_video_frame(video, tmp_path / "damaged.avi", 5)
    with served(damaged) as url, caplog.at_level(logging.WARNING):
        source = open_live_source(url)
        try:
            deadline = time.monotonic() + 10.0
            got = []
            # The reader may pass the damaged frame before the first grab: wait for both.
            while ("damaged JPEG" not in caplog.text or not got) and time.monotonic() < deadline:
                frame = source.grab(timeout_s=0.5)
                if frame is not None:
                    got.append(frame.image)
        finally:
            source.close()
    assert f"{url} #" in caplog.text and ": damaged JPEG (Corrupt JPEG data" in caplog.text
    assert got
    for image in got:
        which_crop(image, crops)  # a close match: the concealed frame is not one


# --- bad sources ----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("spec", "fragment"),
    [
        ("", "expected a device index, stream URL, video file or image folder"),
        ("/nonexistent/frames/", "no such video file or image folder"),
        ("ftp://127.0.0.1/video", "expected a stream URL"),
        ("99", "camera 99: cannot be opened"),
        ("http://127.0.0.1:9/none.mjpg", "cannot be opened"),
    ],
)
def test_bad_sources(spec: str, fragment: str) -> None:
    with raises(fragment) as err:
        open_live_source(spec)
    assert repr(spec) in str(err.value) or spec in str(err.value)


def test_bad_live_options(tmp_path: Path) -> None:
    with raises("expected fps > 0"):
        open_live_source(str(tmp_path), fps=0.0)
    with raises("no such image folder to watch"):
        FolderWatch(tmp_path / "missing")
    fake = tmp_path / "fake.mp4"
    fake.write_text("not a video")
    with raises("fake.mp4: cannot be opened as a video"):
        open_live_source(str(fake))
