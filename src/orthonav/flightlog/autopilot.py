"""Flight logs: where the vehicle was and how it was turned, read from ArduPilot logs by pymavlink.

- MAVLink telemetry logs (``.tlog``): GLOBAL_POSITION_INT (lat, lon, ``relative_alt``: height
  above home) and ATTITUDE (roll, pitch, yaw), from the first vehicle that sent a position.
- DataFlash logs (``.bin``): GPS (first receiver, 3D fix or better) for lat/lon; the height
  above home is POS.RelHomeAlt where the log has it, else the GPS altitude minus that of the
  first fix (the log is assumed to start at home, on the ground); ATT (Roll, Pitch, Yaw).

Times are the ones pymavlink gives each message: for a ``.tlog`` the UNIX time (s) at which
the ground station received it; for a ``.bin`` the UNIX time once the log holds GPS time,
else seconds since the autopilot booted. Frame times must be given on the same clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.geo import LocalFrame

MIN_MESSAGES = 2  # to interpolate between


@dataclass(frozen=True)
class LoggedPoses:
    """Vehicle poses at given times (arrays of one length); angles in degrees, heading in [0, 360)."""

    time_s: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt_agl_m: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.time_s)


@dataclass(frozen=True)
class FlightLog:
    """Positions (``time_s``, lat, lon, height above home) and attitude (``attitude_time_s``,
    heading, pitch, roll), each sorted by time on its own clock ticks."""

    path: Path
    time_s: np.ndarray
    lat: np.ndarray
    lon: np.ndarray
    alt_agl_m: np.ndarray
    attitude_time_s: np.ndarray
    heading_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray

    @property
    def span_s(self) -> tuple[float, float]:
        """The times at which both position and attitude are known (no extrapolation)."""
        return (
            float(max(self.time_s[0], self.attitude_time_s[0])),
            float(min(self.time_s[-1], self.attitude_time_s[-1])),
        )

    @cached_property
    def _frame(self) -> LocalFrame:
        return LocalFrame(float(self.lat[0]), float(self.lon[0]))

    @cached_property
    def _east_north(self) -> tuple[np.ndarray, np.ndarray]:
        return self._frame.to_enu(self.lat, self.lon)

    def at(self, times_s: np.ndarray) -> LoggedPoses:
        """Poses at ``times_s``: position linear in a local ENU frame, heading along the circle."""
        times = np.atleast_1d(np.asarray(times_s, float))
        start, end = self.span_s
        if times.size and (times.min() < start or times.max() > end):
            raise OrthonavError(
                f"{self.path}: poses asked at {times.min():.3f}..{times.max():.3f} s, outside the "
                f"log's {start:.3f}..{end:.3f} s"
            )
        east, north = self._east_north
        lat, lon = self._frame.to_latlon(
            np.interp(times, self.time_s, east), np.interp(times, self.time_s, north)
        )
        # Unwrapped, 359 -> 1 deg interpolates through 0, not back through 180.
        turns = np.unwrap(np.radians(self.heading_deg))
        heading = np.degrees(np.interp(times, self.attitude_time_s, turns)) % 360.0
        return LoggedPoses(
            times,
            np.atleast_1d(lat),
            np.atleast_1d(lon),
            np.interp(times, self.time_s, self.alt_agl_m),
            heading,
            np.interp(times, self.attitude_time_s, self.pitch_deg),
            np.interp(times, self.attitude_time_s, self.roll_deg),
        )


# (N, 4) rows: time, lat, lon, height above home; (M, 4) rows: time, heading, pitch, roll.
Tracks = tuple[list[tuple[float, ...]], list[tuple[float, ...]]]


def _tlog_tracks(messages: dict[str, list[Any]]) -> Tracks:
    positions = [m for m in messages["GLOBAL_POSITION_INT"] if (m.lat, m.lon) != (0, 0)]
    vehicle = positions[0].get_srcSystem() if positions else None
    return (
        [
            (m._timestamp, m.lat * 1e-7, m.lon * 1e-7, m.relative_alt * 1e-3)
            for m in positions
            if m.get_srcSystem() == vehicle
        ],
        [
            (m._timestamp, math.degrees(m.yaw), math.degrees(m.pitch), math.degrees(m.roll))
            for m in messages["ATTITUDE"]
            if m.get_srcSystem() == vehicle
        ],
    )


def _bin_tracks(messages: dict[str, list[Any]]) -> Tracks:
    fixes = [m for m in messages["GPS"] if getattr(m, "I", 0) == 0 and m.Status >= 3]
    times = np.array([m._timestamp for m in fixes])
    home = [m for m in messages["POS"] if hasattr(m, "RelHomeAlt")]
    if home:
        heights = np.interp(times, [m._timestamp for m in home], [m.RelHomeAlt for m in home])
    else:
        heights = np.array([m.Alt - fixes[0].Alt for m in fixes])
    return (
        [(m._timestamp, m.Lat, m.Lng, h) for m, h in zip(fixes, heights, strict=True)],
        [(m._timestamp, m.Yaw, m.Pitch, m.Roll) for m in messages["ATT"]],
    )


@dataclass(frozen=True)
class _Format:
    kind: str  # with its article, for messages
    position: str  # the message type giving GPS positions, named in errors
    attitude: str
    types: tuple[str, ...]  # every type read
    tracks: Callable[[dict[str, list[Any]]], Tracks]
    magic: bytes = b""  # how every such file starts


FORMATS = {
    ".tlog": _Format(
        "a MAVLink telemetry log",
        "GLOBAL_POSITION_INT",
        "ATTITUDE",
        ("GLOBAL_POSITION_INT", "ATTITUDE"),
        _tlog_tracks,
    ),
    # A DataFlash log opens with the FMT record that defines FMT records.
    ".bin": _Format(
        "an ArduPilot DataFlash log", "GPS", "ATT", ("GPS", "POS", "ATT"), _bin_tracks, b"\xa3\x95\x80"
    ),
}


def read_flight_log(path: str | Path) -> FlightLog:
    """Read a ``.tlog`` or ``.bin`` flight log, or raise :class:`OrthonavError` saying what is wrong."""
    path = Path(path)
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise OrthonavError(
            f"{path}: expected an ArduPilot DataFlash log (.bin) or a MAVLink telemetry log (.tlog)"
        )
    if not path.is_file():
        raise OrthonavError(f"{path}: no such flight log")
    positions, attitude = fmt.tracks(_read_messages(path, fmt))
    pos = _track(positions, path, f"GPS positions ({fmt.position} messages with a position fix)")
    att = _track(attitude, path, f"attitude records ({fmt.attitude} messages)")
    lat, lon = pos[:, 1], pos[:, 2]
    if np.any(np.abs(lat) > 90.0) or np.any(np.abs(lon) > 180.0):
        raise OrthonavError(f"{path}: {fmt.position} positions outside [-90, 90] / [-180, 180] degrees")
    return FlightLog(path, pos[:, 0], lat, lon, pos[:, 3], att[:, 0], att[:, 1] % 360.0, att[:, 2], att[:, 3])


def _read_messages(path: Path, fmt: _Format) -> dict[str, list[Any]]:
    with open(path, "rb") as fh:
        if fh.read(len(fmt.magic)) != fmt.magic:
            raise OrthonavError(f"{path}: not {fmt.kind} (it does not start with a log format record)")
    mavutil = _mavutil()
    found: dict[str, list[Any]] = {t: [] for t in fmt.types}
    try:
        conn = mavutil.mavlink_connection(str(path))
        try:
            while (msg := conn.recv_match(type=list(fmt.types))) is not None:
                found[msg.get_type()].append(msg)
        finally:
            conn.close()
    except Exception as exc:  # pymavlink raises plain Exception, ValueError, struct.error...
        raise OrthonavError(f"{path}: not readable as {fmt.kind} ({type(exc).__name__}: {exc})") from None
    return found


def _track(rows: list[tuple[float, ...]], path: Path, what: str) -> np.ndarray:
    """Rows as an array sorted by time, finite, one per time; at least ``MIN_MESSAGES``."""
    data = np.asarray(rows, float).reshape(-1, 4)
    data = data[np.all(np.isfinite(data), axis=1)]
    data = data[np.argsort(data[:, 0], kind="stable")]
    data = data[np.r_[True, np.diff(data[:, 0]) > 0]] if len(data) else data
    if len(data) == 0:
        raise OrthonavError(f"{path}: has no {what}")
    if len(data) < MIN_MESSAGES:
        raise OrthonavError(f"{path}: has only {len(data)} {what}; at least {MIN_MESSAGES} are needed")
    return data


def _mavutil():
    try:
        from pymavlink import mavutil
    except ImportError:
        raise OrthonavError("reading flight logs needs pymavlink: pip install 'orthonav[mavlink]'") from None
    return mavutil
