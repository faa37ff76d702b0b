"""What a replay localizes: frames in order, each with the pose the flight recorded for it.

Two sources: a flight log (.bin/.tlog) with a video or image folder synced by a time offset
(frame ``i`` at log time ``offset_s + i * interval_s``), and geotagged photos, which carry
their own poses. Frames the log does not cover are left out here and counted.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.flightlog import FlightLog, LoggedPoses, read_flight_log
from orthonav.flightlog.photos import PhotoFlight
from orthonav.frames import FrameSource, Unreadable, load_or_unreadable

log = logging.getLogger(__name__)

# Reads frames by position in ``poses``: yields (label, BGR image or why it cannot be decoded)
# in the order asked.
FrameReader = Callable[[Sequence[int]], Iterator[tuple[str, np.ndarray | Unreadable]]]


@dataclass(frozen=True)
class ReplayInput:
    """Frames with their recorded poses (``poses[k]`` is frame ``k`` of ``read``)."""

    name: str
    poses: LoggedPoses
    read: FrameReader
    skipped: dict[str, int] = field(default_factory=dict)  # frames left out, by reason
    info: dict = field(default_factory=dict)  # the inputs, for config.json


def flight_input(log_path: Path, frames: FrameSource, offset_s: float, every: int = 1) -> ReplayInput:
    """Every ``every``-th frame inside the log's time span, with the logged pose at its time."""
    _check_every(every)
    flight = read_flight_log(log_path)
    times = offset_s + np.arange(frames.count) * frames.interval_s
    chosen = np.flatnonzero(np.arange(frames.count) % every == 0)
    inside = chosen[_in_span(times[chosen], flight, frames.name)]
    _warn_uncovered_log(times[chosen], flight, frames.name, every * frames.interval_s)
    chosen_by_k = inside.tolist()

    def read(ks: Sequence[int]) -> Iterator[tuple[str, np.ndarray | Unreadable]]:
        return frames.read([chosen_by_k[k] for k in ks])

    info = {
        "log": str(log_path),
        "frames": frames.name,
        "frame_count": frames.count,
        "interval_s": frames.interval_s,
        "offset_s": offset_s,
        "log_span_s": list(flight.span_s),
    }
    skipped = {"outside the log": len(chosen) - len(inside)}
    return ReplayInput(frames.name, flight.at(times[inside]), read, skipped, info)


def photo_input(flight: PhotoFlight, every: int = 1) -> ReplayInput:
    """Every ``every``-th photo, with the pose its own EXIF/XMP records."""
    _check_every(every)
    photos = flight.photos[::every]
    poses = PhotoFlight(flight.source, photos).poses()

    def read(ks: Sequence[int]) -> Iterator[tuple[str, np.ndarray | Unreadable]]:
        for k in ks:
            yield photos[k].path.name, load_or_unreadable(photos[k].path)

    info = {"photos": str(flight.source), "photo_count": len(flight)}
    return ReplayInput(flight.source.name, poses, read, {}, info)


def _check_every(every: int) -> None:
    if every < 1:
        raise OrthonavError(f"every: expected to use every N-th frame with N >= 1, got N = {every}")


def _in_span(times: np.ndarray, flight: FlightLog, name: str) -> np.ndarray:
    """Which frame times the log covers; a warning for those it does not, an error if none."""
    start, end = flight.span_s
    inside = (times >= start) & (times <= end)
    if not inside.any():
        raise OrthonavError(
            f"{name}: no frame falls in the flight log {flight.path.name}: the log covers "
            f"{start:.2f}..{end:.2f} s, the frames {times[0]:.2f}..{times[-1]:.2f} s; check the time "
            "offset of the first frame (--offset, on the log's clock)"
        )
    if not inside.all():
        log.warning(
            "%s: %d of %d frames lie outside the log %s (it covers %.2f..%.2f s, the frames %.2f..%.2f s): "
            "skipped",
            name,
            int((~inside).sum()),
            len(times),
            flight.path.name,
            start,
            end,
            times[0],
            times[-1],
        )
    return inside


def _warn_uncovered_log(times: np.ndarray, flight: FlightLog, name: str, spacing_s: float) -> None:
    """Frames that stop before the log does (a video shorter than the flight) are worth a word;
    less than one frame spacing at either end is just where the frames fell."""
    start, end = flight.span_s
    first, last = max(times[0], start), min(times[-1], end)
    if max(first - start, end - last) > spacing_s:
        log.warning(
            "%s: frames for %.1f s of the %.1f s logged in %s; none for %.1f s at its start and %.1f s at "
            "its end (frames shorter than the flight, or an offset that is off)",
            name,
            last - first,
            end - start,
            flight.path.name,
            first - start,
            end - last,
        )
