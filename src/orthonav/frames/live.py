"""Live camera sources for the companion loop: the newest frame, stamped with its capture time.

A localizer is slower than a camera, so a live source never queues: ``grab`` returns the newest
frame not returned before, and frames that came and went in between are dropped. Capture times
are UNIX seconds, the clock the navigation filter compensates latency with.

- ``"0"``, ``"1"``...: an OpenCV camera device; ``rtsp://``, ``udp://``, ``http(s)://``...: a
  network stream. Both are read on a thread (OpenCV buffers frames; reading on demand would give
  frames seconds old), stamped when OpenCV hands them over, and reopened if they stop.
- A video file: played in real time from the moment it is opened; frame ``i`` is stamped
  ``start + i / fps``.
- A folder: watched for new images (a camera app, or the sim vehicle, writing there). A name
  ``frame_<unix microseconds>.jpg`` (:func:`frame_filename`) gives the capture time, else the
  file's modification time. Hidden files (an atomic writer's temporary names) are ignored;
  files that are partial, damaged (a JPEG's data lost or zeroed: libjpeg's warnings are errors)
  or not images are skipped with a warning that says why, and read again only once they change.
"""

from __future__ import annotations

import logging
import math
import os
import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from orthonav.errors import OrthonavError
from orthonav.frames.offline import IMAGE_SUFFIXES, CheckedCapture, decode_frame, open_video

log = logging.getLogger(__name__)

STREAM_SCHEMES = ("rtsp", "rtsps", "rtmp", "udp", "tcp", "http", "https")
_FRAME_NAME = re.compile(r"frame_(\d{1,19})")
_STREAM_TIMEOUT_MS = 5000  # open and read; without it FFmpeg may wait forever on a silent UDP port


@dataclass(frozen=True, eq=False)
class Frame:
    """One camera frame: BGR uint8 image, capture time (UNIX s), and a label for logs."""

    image: np.ndarray
    capture_time_s: float
    label: str


class LiveSource(Protocol):
    name: str

    def grab(self, timeout_s: float) -> Frame | None:
        """The newest frame not returned before, or None if none came within ``timeout_s``."""
        ...

    def close(self) -> None: ...


def frame_filename(capture_time_s: float, ext: str = ".jpg") -> str:
    """``frame_<unix microseconds><ext>``: a name that carries its capture time to a watched folder."""
    return f"frame_{round(capture_time_s * 1e6):d}{ext}"


def capture_time_from_name(path: Path) -> float | None:
    """The capture time a :func:`frame_filename` name carries, or None for other names."""
    match = _FRAME_NAME.fullmatch(path.stem)
    return int(match.group(1)) / 1e6 if match else None


def open_live_source(spec: str, fps: float | None = None, existing: bool = False) -> LiveSource:
    """A device index, stream URL, video file or image folder (see the module docstring).

    ``fps``: the rate asked of a device, or a video's playback rate (default its own); a watched
    folder ignores it. ``existing``: a watched folder also returns the images already there.
    """
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise OrthonavError(f"camera frame rate: expected fps > 0, got {fps}")
    text = spec.strip()
    if not text:
        raise OrthonavError(
            "camera source '': expected a device index, stream URL, video file or image folder"
        )
    if text.isdigit():
        return CameraStream(int(text), f"camera {text}", fps)
    if "://" in text:
        scheme = text.split("://", 1)[0].lower()
        if scheme not in STREAM_SCHEMES:
            raise OrthonavError(
                f"camera source {spec!r}: expected a stream URL ({', '.join(STREAM_SCHEMES)})"
            )
        return CameraStream(text, text, fps)
    path = Path(text)
    if path.is_dir():
        return FolderWatch(path, existing)
    if path.is_file():
        return VideoPlayback(path, fps)
    raise OrthonavError(
        f"camera source {spec!r}: no such video file or image folder, and not a device index (0, 1...) "
        "or stream URL (rtsp://, udp://, http://...)"
    )


class CameraStream:
    """An OpenCV device or stream, read continuously on a thread that keeps only the newest frame."""

    reopen_s = 1.0

    def __init__(self, target: int | str, name: str, fps: float | None = None) -> None:
        self.name = name
        self._target = target
        self._fps = fps
        capture = self._open()
        if not capture.is_opened():
            raise OrthonavError(
                f"{name}: cannot be opened (no such device, stream not reachable, or a format OpenCV "
                "cannot read)"
            )
        self._cond = threading.Condition()
        self._latest: Frame | None = None
        self._count = 0  # frames read
        self._returned = 0  # ``_count`` when ``grab`` last returned
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(capture,), name=name, daemon=True)
        self._thread.start()

    def _open(self) -> CheckedCapture:
        if isinstance(self._target, int):
            capture = cv2.VideoCapture(self._target)
        else:
            timeouts = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, _STREAM_TIMEOUT_MS]
            timeouts += [cv2.CAP_PROP_READ_TIMEOUT_MSEC, _STREAM_TIMEOUT_MS]
            capture = cv2.VideoCapture(self._target, cv2.CAP_FFMPEG, timeouts)
        if self._fps and capture.isOpened():
            capture.set(cv2.CAP_PROP_FPS, self._fps)
        return CheckedCapture(capture, check=not isinstance(self._target, int))

    def _run(self, capture: CheckedCapture) -> None:
        stopped_at: float | None = None
        damaged = False  # the frame before was damaged: said once for a run of them
        while not self._stop.is_set():
            try:
                image = capture.read(f"{self.name} #{self._count + 1}") if capture.is_opened() else None
            except OrthonavError as exc:
                if not damaged:
                    log.warning("%s; skipped, as are the damaged frames right after it", exc)
                damaged = True
                continue
            damaged = False
            if image is not None:
                if stopped_at is not None:
                    log.warning("%s: frames again after %.1f s", self.name, time.time() - stopped_at)
                    stopped_at = None
                self._publish(image)
                continue
            if stopped_at is None:
                stopped_at = time.time()
                log.warning("%s: stopped delivering frames; reopening every %g s", self.name, self.reopen_s)
            capture.release()
            if self._stop.wait(self.reopen_s):
                break
            capture = self._open()
        capture.release()

    def _publish(self, image: np.ndarray) -> None:
        with self._cond:
            self._count += 1
            self._latest = Frame(image, time.time(), f"{self.name} #{self._count}")
            self._cond.notify_all()

    def grab(self, timeout_s: float) -> Frame | None:
        with self._cond:
            if not self._cond.wait_for(lambda: self._count > self._returned, timeout_s):
                return None
            self._returned = self._count
            return self._latest

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0 * self.reopen_s)


class VideoPlayback:
    """A video file as if its camera were live: the frame due now, decoded when asked for."""

    def __init__(self, path: Path, fps: float | None = None) -> None:
        self.name = path.name
        self._capture = CheckedCapture(open_video(path))
        own = self._capture.capture.get(cv2.CAP_PROP_FPS)
        self.fps = fps or own
        if not (math.isfinite(self.fps) and self.fps > 0):
            self._capture.release()
            raise OrthonavError(f"{path}: the video does not give its frame rate; give one (fps)")
        self._start_s = time.time()
        self._returned = -1  # index of the last frame returned
        self._ended = False

    def _due(self) -> int:
        return math.floor((time.time() - self._start_s) * self.fps)

    def grab(self, timeout_s: float) -> Frame | None:
        wait_s = self._start_s + (self._returned + 1) / self.fps - time.time()
        if self._ended or wait_s > timeout_s:
            time.sleep(timeout_s)  # as a camera that has nothing new: the caller waits, then hears None
            return None
        time.sleep(max(0.0, wait_s))
        return self._decode(max(self._due(), self._returned + 1))

    def _decode(self, index: int) -> Frame | None:
        label = f"{self.name} frame {index}"
        try:
            image = self._capture.read_at(index, label)
        except OrthonavError as exc:  # a damaged frame is passed over, as a watched folder's is
            log.warning("%s; skipped", exc)
            self._returned = index
            return None
        if image is None:
            self._ended = True
            log.warning("%s: the video ended after %d frames", self.name, self._capture.position)
            return None
        self._returned = index
        return Frame(image, self._start_s + index / self.fps, label)

    def close(self) -> None:
        self._capture.release()


@dataclass
class _Seen:
    """What a folder watch has already dealt with: returned or dropped names, and bad files."""

    names: set[str] = field(default_factory=set)
    bad: dict[str, tuple[int, int]] = field(default_factory=dict)  # name -> (size, mtime_ns) when bad


class FolderWatch:
    """New image files in a folder, newest first; older new ones are dropped as stale.

    The companion asks for a frame every few milliseconds and a camera's folder grows all
    flight (7200 frames an hour at 2 per second), and listing it costs more the more it holds.
    So the folder is listed only when it may hold something new: its modification time changed
    (a file added, renamed or removed), a file skipped as partial changed, or ``rescan_s``
    passed (file systems whose times are coarse). Names already dealt with are passed over
    before anything else.
    """

    poll_s = 0.05
    rescan_s = 1.0

    def __init__(self, folder: Path, existing: bool = False) -> None:
        if not folder.is_dir():
            raise OrthonavError(f"{folder}: no such image folder to watch")
        self.folder = folder
        self.name = str(folder)
        self._seen = _Seen()
        self._listed: tuple[int | None, float] | None = None  # (folder mtime, monotonic time)
        self.passed_over = 0  # images there before watching began, not returned (``existing`` False)
        if not existing:
            names = {entry.name for entry in self._images()}
            self._seen.names.update(names)
            self.passed_over = len(names)
        self.dropped = 0  # new frames never returned because a newer one was

    def _images(self) -> list[os.DirEntry]:
        """The image files not dealt with yet (hidden names are a writer's temporary files)."""
        try:
            entries = list(os.scandir(self.folder))
        except OSError as exc:
            log.warning("%s: cannot be listed (%s)", self.folder, exc.strerror or exc)
            return []
        seen = self._seen.names
        return [
            e
            for e in entries
            if e.name not in seen
            and not e.name.startswith(".")
            and os.path.splitext(e.name)[1].lower() in IMAGE_SUFFIXES
            and e.is_file()
        ]

    def _may_have_new(self) -> bool:
        """Whether the folder is worth listing now (see the class)."""
        try:
            stamp: int | None = os.stat(self.folder).st_mtime_ns
        except OSError:
            stamp = None
        now = time.monotonic()
        if self._listed is None or stamp != self._listed[0] or now - self._listed[1] >= self.rescan_s:
            self._listed = (stamp, now)  # before listing: a file added meanwhile changes it again
            return True
        return self._skipped_changed()

    def _skipped_changed(self) -> bool:
        """Whether a file skipped as partial or unreadable has changed (or gone) since."""
        for name, signature in self._seen.bad.items():
            try:
                stat = os.stat(self.folder / name)
            except OSError:
                return True
            if (stat.st_size, stat.st_mtime_ns) != signature:
                return True
        return False

    def grab(self, timeout_s: float) -> Frame | None:
        deadline = time.monotonic() + timeout_s
        while (frame := self._newest()) is None:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            time.sleep(min(self.poll_s, left))
        return frame

    def _new_images(self) -> list[tuple[float, str, os.DirEntry]]:
        """(capture time, name, entry) of the images not dealt with yet, oldest first."""
        found = []
        for entry in self._images():
            try:
                if self._is_new(entry):
                    found.append((_capture_time(entry), entry.name, entry))
            except OSError:  # removed since the folder was listed
                continue
        return sorted(found)  # names are unique: the entries themselves are never compared

    def _newest(self) -> Frame | None:
        if not self._may_have_new():
            return None
        new = self._new_images()
        for k in range(len(new) - 1, -1, -1):
            capture_time, name, entry = new[k]
            try:
                image = _read_complete(Path(entry.path))
            except OrthonavError as exc:
                self._skip(entry, str(exc))
                continue
            self.dropped += k
            self._seen.names.update(n for _, n, _ in new[: k + 1])
            return Frame(image, capture_time, name)
        return None

    def _is_new(self, entry: os.DirEntry) -> bool:
        if entry.name in self._seen.names:
            return False
        bad = self._seen.bad.get(entry.name)
        return bad is None or bad != _signature(entry)

    def _skip(self, entry: os.DirEntry, reason: str) -> None:
        """A partial or broken file: warn once, and look again only when it changes."""
        try:
            self._seen.bad[entry.name] = _signature(entry)
        except OSError:  # gone already: nothing to look at again
            self._seen.names.add(entry.name)
        log.warning("%s; skipped until it changes", reason)

    def close(self) -> None:
        """Nothing to release: the folder is only listed and read."""


def _signature(entry: os.DirEntry) -> tuple[int, int]:
    stat = entry.stat()
    return stat.st_size, stat.st_mtime_ns


def _capture_time(entry: os.DirEntry) -> float:
    named = capture_time_from_name(Path(entry.name))
    return named if named is not None else entry.stat().st_mtime


def _read_complete(path: Path) -> np.ndarray:
    """The image, or an error saying why not: unreadable, cut short (still being written),
    damaged, or not an image."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise OrthonavError(f"{path}: cannot be read ({exc.strerror or exc})") from exc
    if not _looks_complete(data, path.suffix.lower()):
        raise OrthonavError(f"{path}: partial (no end marker yet)")
    return decode_frame(data, path)


def _looks_complete(data: bytes, suffix: str) -> bool:
    """JPEG and PNG end with a marker: a file without it is still being written, and is looked
    at again when it changes. Damage before the marker is :func:`decode_frame`'s to find."""
    if suffix in (".jpg", ".jpeg"):
        return data.rstrip(b"\x00").endswith(b"\xff\xd9")
    if suffix == ".png":
        return b"IEND" in data[-12:]
    return bool(data)
