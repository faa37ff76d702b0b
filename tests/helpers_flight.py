"""Flight logs written independently of the code under test: a straight track logged as MAVLink
(.tlog) and DataFlash (.bin) records with pymavlink, for the flight-log and replay tests."""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from orthonav.geo import destination

mavlink = pytest.importorskip(
    "pymavlink.dialects.v20.ardupilotmega", reason="flight logs need the 'mavlink' extra (pymavlink)"
)

T0 = 1_700_000_000.0  # UNIX time of the first log record
ALT_M = 500.0
PITCH_DEG, ROLL_DEG = 2.0, -1.0


@dataclass(frozen=True)
class Track:
    """A straight, level track at constant speed through (lat0, lon0) ``mid_s`` after T0."""

    lat0: float
    lon0: float
    heading_deg: float = 60.0
    speed_mps: float = 15.0
    mid_s: float = 10.0

    def at(self, t: float) -> tuple[float, float]:
        """Position ``t`` seconds after T0 (geodesic, not through the code under test)."""
        dist = self.speed_mps * (t - self.mid_s)
        return destination(
            self.lat0, self.lon0, self.heading_deg if dist >= 0 else self.heading_deg + 180, abs(dist)
        )


def write_tlog(
    path: Path,
    track: Track,
    positions: bool = True,
    alt_m: Callable[[float], float] = lambda t: ALT_M,
    seconds: float = 20.0,
) -> Path:
    """GLOBAL_POSITION_INT at 5 Hz and ATTITUDE at 10 Hz (pitch PITCH_DEG, roll ROLL_DEG), each
    record an 8-byte big-endian UNIX microsecond stamp followed by the packed MAVLink message
    (the .tlog format)."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    yaw = math.radians((track.heading_deg + 180) % 360 - 180)
    records = []
    for i in range(int(seconds * 10) + 1):
        t = i * 0.1
        if positions and i % 2 == 0:
            lat, lon = track.at(t)
            msg = mavlink.MAVLink_global_position_int_message(
                int(t * 1000), round(lat * 1e7), round(lon * 1e7), 0, round(alt_m(t) * 1000), 0, 0, 0, 0
            )
            records.append((t, msg))
        att = mavlink.MAVLink_attitude_message(
            int(t * 1000) + 50, math.radians(ROLL_DEG), math.radians(PITCH_DEG), yaw, 0, 0, 0
        )
        records.append((t + 0.05, att))
    with open(path, "wb") as fh:
        for t, msg in records:
            fh.write(struct.pack(">Q", round((T0 + t) * 1e6)) + msg.pack(mav))
    return path


def _df_format(type_id: int, name: str, fmt: str, columns: str) -> bytes:
    length = 3 + struct.calcsize("<" + _df_struct(fmt))
    return b"\xa3\x95\x80" + struct.pack(
        "<BB4s16s64s", type_id, length, name.encode(), fmt.encode(), columns.encode()
    )


def _df_struct(fmt: str) -> str:
    """DataFlash format letters -> struct letters (L: latitude/longitude, int32 x 1e7)."""
    return fmt.replace("L", "i")


def write_bin(path: Path, track: Track, home_alt: bool) -> Path:
    """A DataFlash log: FMT records, then GPS (with GPS week/ms), ATT and optionally POS.

    GPS altitude is AMSL: 300 m of ground plus ``ALT_M`` once airborne; POS.RelHomeAlt is the
    height above home. Boot time 10 s at T0.
    """
    gps_fmt, att_fmt, pos_fmt = "QBIHLLf", "Qfff", "QLLff"
    data = _df_format(130, "GPS", gps_fmt, "TimeUS,Status,GMS,GWk,Lat,Lng,Alt")
    data += _df_format(131, "ATT", att_fmt, "TimeUS,Roll,Pitch,Yaw")
    data += _df_format(132, "POS", pos_fmt, "TimeUS,Lat,Lng,Alt,RelHomeAlt")
    # GPS time of T0: seconds since 1980-01-06 plus 18 leap seconds (pymavlink's convention).
    gps_s = T0 - 315964800.0 + 18.0
    week, week_ms = int(gps_s // 604800), round((gps_s % 604800) * 1000)
    for i in range(21):
        t = i * 0.5
        us = round((10.0 + t) * 1e6)
        lat, lon = track.at(t)
        height = 0.0 if i == 0 else ALT_M  # the first fix is on the ground at home
        lat_e7, lon_e7 = round(lat * 1e7), round(lon * 1e7)
        data += b"\xa3\x95\x82" + struct.pack(
            "<" + _df_struct(gps_fmt), us, 3, week_ms + round(t * 1000), week, lat_e7, lon_e7, 300.0 + height
        )
        data += b"\xa3\x95\x83" + struct.pack(
            "<" + _df_struct(att_fmt), us + 20_000, ROLL_DEG, PITCH_DEG, track.heading_deg
        )
        if home_alt:
            data += b"\xa3\x95\x84" + struct.pack(
                "<" + _df_struct(pos_fmt), us, lat_e7, lon_e7, 300.0 + height, height + 1.0
            )
    path.write_bytes(data)
    return path
