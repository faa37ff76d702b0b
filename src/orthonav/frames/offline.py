"""Recorded frames read in order: an image folder or a video file, at a known frame interval.

Used where frames are matched with a flight log after the flight (``correction train`` with
``--flight-*``, ``orthonav replay``): frame ``i`` was taken ``i * interval_s`` after the first.
"""

from __future__ import annotations

import io
import logging
import math
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
import simplejpeg
from PIL import Image, UnidentifiedImageError

from orthonav.camera import Camera
from orthonav.errors import OrthonavError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp"}
# Video codecs that code each frame as one JPEG (Motion JPEG), by their FourCC.
MJPEG_FOURCCS = frozenset({"MJPG", "mjpg", "JPEG", "jpeg"})


@dataclass(frozen=True)
class Unreadable:
    """A recorded frame that cannot be decoded (damaged, cut short), with the reason: a run over
    a flight rejects it as one frame and goes on, as one bad frame is not the end of a flight."""

    reason: str


class FrameSource(Protocol):
    """Frames taken ``interval_s`` apart; ``read`` yields (label, BGR image, or why the frame
    cannot be decoded) for ascending indices."""

    name: str
    count: int
    interval_s: float

    def read(self, indices: Sequence[int]) -> Iterator[tuple[str, np.ndarray | Unreadable]]: ...


# File names of the pictures of a frame's matches written beside the frames (not frames).
MATCHES_PREFIX = "matches_"


def list_images(folder: Path) -> list[Path]:
    """The image files of a folder sorted by name (frame order), or a clear error if none.

    Pictures of matches that a mission writes beside its frames (``matches_*``) are not frames.
    """
    images = sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file() and not p.name.startswith(MATCHES_PREFIX)
    )
    if not images:
        raise OrthonavError(f"{folder}: no image files ({', '.join(sorted(IMAGE_SUFFIXES))})")
    return images


class ImageFrames:
    """Image files in the order given (e.g. sorted by name), ``interval_s`` apart."""

    def __init__(self, files: Sequence[Path], interval_s: float) -> None:
        if not files:
            raise OrthonavError("flight frames: no image files given")
        if not (math.isfinite(interval_s) and interval_s > 0):
            raise OrthonavError(f"flight frame interval: expected seconds > 0, got {interval_s}")
        self.files = list(files)
        self.name = self.files[0].parent.name
        self.count = len(self.files)
        self.interval_s = interval_s

    def read(self, indices: Sequence[int]) -> Iterator[tuple[str, np.ndarray | Unreadable]]:
        for index in indices:
            yield self.files[index].name, load_or_unreadable(self.files[index])


class VideoFrames:
    """A video file read in order with OpenCV; frames not asked for are grabbed, not decoded."""

    def __init__(self, path: Path) -> None:
        if not path.is_file():
            raise OrthonavError(f"{path}: no such video file")
        self.path = path
        self.name = path.name
        capture = open_video(path)
        fps, count = capture.get(cv2.CAP_PROP_FPS), int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        capture.release()
        if not (math.isfinite(fps) and fps > 0 and count > 0):
            raise OrthonavError(
                f"{path}: the video does not give its frame rate and length ({fps} fps, {count} frames)"
            )
        self.count = count
        self.interval_s = 1.0 / fps

    def read(self, indices: Sequence[int]) -> Iterator[tuple[str, np.ndarray | Unreadable]]:
        capture = CheckedCapture(open_video(self.path))
        try:
            for index in indices:
                label = f"{self.name} frame {index}"
                try:
                    image = capture.read_at(index, label)
                except OrthonavError as exc:
                    image = Unreadable(str(exc))
                if image is None:
                    # Containers often announce a frame or two more than they hold.
                    log.warning(
                        "%s: the video ends at frame %d, it announces %d",
                        self.path,
                        capture.position,
                        self.count,
                    )
                    return
                yield label, image
        finally:
            capture.release()


def open_video(path: Path) -> cv2.VideoCapture:
    """An opened OpenCV capture of a video file, or a clear error."""
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise OrthonavError(f"{path}: cannot be opened as a video (expected e.g. MP4, MKV or AVI)")
    return capture


class CheckedCapture:
    """An OpenCV capture whose frames are checked as image files are, where the codec allows it.

    FFmpeg's decoders conceal a damaged frame (grey or smeared blocks) and OpenCV hands it over
    as good. A Motion JPEG video is one JPEG a frame, so its packets are taken undecoded and
    decoded strictly as a file's JPEG is (:func:`decode_frame`). Codecs that predict a frame from
    others (H.264, H.265) give no verdict per frame through OpenCV: their frames pass unchecked,
    as do a camera device's (``check=False``: OpenCV's device backends are not FFmpeg's).
    """

    def __init__(self, capture: cv2.VideoCapture, check: bool = True) -> None:
        self.capture = capture
        self.position = 0  # the index of the next frame (read_at's)
        code = int(max(capture.get(cv2.CAP_PROP_FOURCC), 0))  # -1 where the capture did not open
        fourcc = code.to_bytes(4, "little").decode("latin-1")
        self.checked = check and fourcc in MJPEG_FOURCCS and bool(capture.set(cv2.CAP_PROP_FORMAT, -1))

    def is_opened(self) -> bool:
        return bool(self.capture.isOpened())

    def grab(self) -> bool:
        return bool(self.capture.grab())

    def read(self, label: str) -> np.ndarray | None:
        """The next frame, None at the end; an error naming ``label`` where the frame is damaged."""
        ok, image = self.capture.read()
        if not ok or image is None:
            return None
        return decode_frame(image.tobytes(), label) if self.checked else image

    def read_at(self, index: int, label: str) -> np.ndarray | None:
        """Frame ``index`` (not before :attr:`position`), the frames before it grabbed, not
        decoded; None past the end (:attr:`position` then counts the frames the video holds). A
        damaged frame raises, and is passed over all the same."""
        while self.position < index and self.capture.grab():
            self.position += 1
        if self.position != index:
            return None
        self.position += 1
        image = self.read(label)
        if image is None:
            self.position -= 1  # there was no such frame
        return image

    def release(self) -> None:
        self.capture.release()


def open_frames(
    path: Path, interval_s: float | None, option: str = "--frames", interval_option: str = "--interval"
) -> FrameSource:
    """A video (its frame rate sets the interval) or an image folder (``interval_s`` needed).

    ``option`` and ``interval_option`` name the inputs in errors (the CLI's option names).
    """
    if not path.exists():
        raise OrthonavError(f"{option} {path}: no such video file or image folder")
    if path.is_dir():
        if interval_s is None:
            raise OrthonavError(
                f"{interval_option}: missing; {path} is an image folder: give the seconds between its frames"
            )
        return ImageFrames(list_images(path), interval_s)
    if interval_s is not None:
        raise OrthonavError(f"{interval_option}: {path} is a video: its frame rate sets the interval")
    return VideoFrames(path)


def check_frame_size(image: np.ndarray, camera: Camera, label: str) -> None:
    """A frame of another size means another camera: an error for the run, not a skipped frame."""
    if image.shape[:2] != (camera.height, camera.width):
        raise OrthonavError(
            f"{label}: {image.shape[1]}x{image.shape[0]} px, but the camera is "
            f"{camera.width}x{camera.height}; give the flight's camera"
        )


def load_frame(path: str | Path) -> np.ndarray:
    """Read a camera frame (any format OpenCV decodes) as BGR uint8, or raise a clear error."""
    path = Path(path)
    if not path.is_file():
        raise OrthonavError(f"{path}: no such frame file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OrthonavError(f"{path}: cannot be read ({exc.strerror or exc})") from exc
    return decode_frame(data, path)


def load_or_unreadable(path: Path) -> np.ndarray | Unreadable:
    """A recorded frame, or why it cannot be read (see :class:`Unreadable`)."""
    try:
        return load_frame(path)
    except OrthonavError as exc:
        return Unreadable(str(exc))


JPEG_START = b"\xff\xd8\xff"
EXIF_ORIENTATION = 0x0112  # the EXIF tag


def decode_frame(data: bytes, path: str | Path) -> np.ndarray:
    """The frame in an image file's bytes as BGR uint8; damaged or oversized data raises an error.

    A JPEG with lost or zeroed data still decodes in OpenCV, which only prints libjpeg's
    "Corrupt JPEG data" warning and fills the gap with grey or garbage: such a frame was localized
    over 100 m off at a small claimed sigma. So a JPEG is decoded by libjpeg-turbo with its
    warnings as errors. PNG (libpng checks every chunk's CRC) and other formats go to OpenCV.
    """
    if data.startswith(JPEG_START):
        return _decode_jpeg(data, path)
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    except cv2.error as exc:  # e.g. more pixels than CV_IO_MAX_IMAGE_PIXELS
        raise OrthonavError(f"{path}: cannot be decoded as an image ({_cv2_reason(exc)})") from exc
    if image is None:
        raise OrthonavError(
            f"{path}: cannot be decoded as an image (damaged, cut short, or not JPEG, PNG, TIFF...)"
        )
    return image


def _decode_jpeg(data: bytes, path: str | Path) -> np.ndarray:
    """A JPEG decoded strictly (see :func:`decode_frame`), turned upright as OpenCV would."""
    try:
        image = simplejpeg.decode_jpeg(data, colorspace="BGR", strict=True)
    except ValueError as exc:  # libjpeg's own words: "Premature end of JPEG file", "Corrupt JPEG data..."
        raise OrthonavError(f"{path}: damaged JPEG ({exc})") from exc
    if _exif_orientation(data) in (None, 1):
        return image
    # OpenCV turns a frame by its EXIF orientation: keep what a camera JSON was calibrated on.
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)


def _exif_orientation(data: bytes) -> int | None:
    """The EXIF orientation tag of a JPEG (1: upright), None where there is none or it is unreadable."""
    try:
        return Image.open(io.BytesIO(data)).getexif().get(EXIF_ORIENTATION)
    except (OSError, UnidentifiedImageError, SyntaxError, ValueError):
        return None


def _cv2_reason(exc: cv2.error) -> str:
    """OpenCV's assertion in words a user can act on."""
    if "CV_IO_MAX_IMAGE_PIXELS" in str(exc):
        limit = os.environ.get("CV_IO_MAX_IMAGE_PIXELS", str(2**30))
        return f"more than {limit} pixels, OpenCV's limit (environment variable CV_IO_MAX_IMAGE_PIXELS)"
    return str(exc).strip().splitlines()[-1]
