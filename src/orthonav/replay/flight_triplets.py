"""Training triplets from a real flight: camera frames synced by time with the flight log.

Frame ``i`` (counting every frame of the video or image folder) was taken at log time
``offset_s + i * interval_s``: ``offset_s`` is the log time of the first frame, on the log's
clock (see :mod:`orthonav.flightlog.autopilot`), ``interval_s`` the video's frame period or the
given spacing of an image folder's frames (sorted by name).

The logged pose is taken as the truth: the anchor is the frame orthorectified with it, the
region is the map around the logged position (GNSS errors of a few metres stay within a
pixel of ~5 m/px views; on finer maps they are label noise). The temporal negative is where
the logged position lay ``seconds_earlier`` before, so a frame needs that much log before it.
"""

from __future__ import annotations

import logging

import numpy as np
from tqdm import tqdm

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.flightlog import FlightLog, LoggedPoses
from orthonav.frames import FrameSource, Unreadable, check_frame_size
from orthonav.frames.views import ViewGeometry, Views, make_views
from orthonav.geo import GeoRaster, LocalFrame
from orthonav.models.dataset import TripletConfig, TripletSet, views_to_triplets
from orthonav.types import Prior

log = logging.getLogger(__name__)


def flight_triplets(
    frames: FrameSource,
    flight: FlightLog,
    raster: GeoRaster,
    camera: Camera,
    config: TripletConfig,
    offset_s: float,
    every: int = 1,
    attitude: bool = True,
    progress: bool = False,
) -> TripletSet:
    """Triplets from every ``every``-th frame inside the log, at the logged poses, over ``raster``.

    ``attitude=False`` (a camera on a nadir gimbal) ignores the vehicle's pitch and roll.
    Frames whose views cannot be made (search region off the map, too low...) are skipped and
    counted; an error if none is left.
    """
    if every < 1:
        raise OrthonavError(f"flight frames: expected to use every N-th frame with N >= 1, got N = {every}")
    times = offset_s + np.arange(frames.count) * frames.interval_s
    indices = _indices_in_log(times, flight, config.seconds_earlier, every, frames.name)
    poses = flight.at(times[indices])
    earlier = flight.at(times[indices] - config.seconds_earlier)
    views: list[Views] = []
    temporal: list[tuple[float, float]] = []
    skipped: list[str] = []
    read = frames.read(indices.tolist())
    for k, (label, image) in enumerate(
        tqdm(read, total=len(indices), desc="flight", disable=not progress, leave=False)
    ):
        if isinstance(image, Unreadable):
            skipped.append(image.reason)
            continue
        check_frame_size(image, camera, label)
        try:
            view = make_views(
                raster, camera, image, _prior(poses, k, attitude), config.size_px, config.search_factor
            )
        except OrthonavError as exc:
            skipped.append(f"{label}: {exc}")
            continue
        views.append(view)
        temporal.append(_temporal_px(view.geometry, earlier, k))
    if not views:
        reason = f"e.g. {skipped[0]}" if skipped else "none could be read"
        raise OrthonavError(f"{frames.name}: no frame in the log's time span makes a sample; {reason}")
    if skipped:
        log.warning(
            "%s: %d of %d frames skipped, e.g. %s", frames.name, len(skipped), len(indices), skipped[0]
        )
    return views_to_triplets(views, temporal, f"flight {frames.name}")


def _indices_in_log(
    times: np.ndarray, flight: FlightLog, seconds_earlier: float, every: int, name: str
) -> np.ndarray:
    """Frames every ``every``-th whose time and ``seconds_earlier`` before lie in the log."""
    start, end = flight.span_s
    inside = (times - seconds_earlier >= start) & (times <= end)
    inside[np.arange(len(times)) % every != 0] = False
    if not inside.any():
        raise OrthonavError(
            f"{name}: no frame falls in the flight log {flight.path.name}: the log covers "
            f"{start:.2f}..{end:.2f} s, the frames {times[0]:.2f}..{times[-1]:.2f} s (each frame needs "
            f"{seconds_earlier:g} s of log before it); check the time offset of the first frame"
        )
    return np.flatnonzero(inside)


def _prior(poses: LoggedPoses, k: int, attitude: bool) -> Prior:
    tilt = (float(poses.pitch_deg[k]), float(poses.roll_deg[k])) if attitude else (None, None)
    return Prior(
        float(poses.lat[k]),
        float(poses.lon[k]),
        float(poses.alt_agl_m[k]),
        float(poses.heading_deg[k]),
        *tilt,
    )


def _temporal_px(geometry: ViewGeometry, earlier: LoggedPoses, k: int) -> tuple[float, float]:
    """Where the logged position ``seconds_earlier`` back lies, in the heading-up view (px)."""
    frame = LocalFrame(geometry.prior_lat, geometry.prior_lon)
    east, north = frame.to_enu(float(earlier.lat[k]), float(earlier.lon[k]))
    return geometry.en_to_offset(float(east), float(north))
