"""Geotagged drone photos read as a flight: DJI-style EXIF and XMP.

- EXIF GPS: latitude, longitude, altitude above mean sea level (GPSAltitude); ``DateTimeOriginal``
  (with ``SubSecTimeOriginal`` and ``OffsetTimeOriginal`` where written) for the capture time.
  DJI writes local time without a zone: such times are read as UTC, so differences between
  photos are right but the absolute time may be off by the zone.
- DJI XMP (``drone-dji:`` attributes or elements): ``RelativeAltitude`` (height above the
  take-off point, the altitude a localizer needs over flat ground), ``GimbalYawDegree``,
  ``GimbalPitchDegree`` (-90 = nadir), ``GimbalRollDegree`` and ``FlightYawDegree``. A photo
  without them keeps its EXIF position and time; its height and attitude are unknown (NaN in
  :meth:`PhotoFlight.poses`), with a warning.
- Intrinsics: EXIF focal length over the sensor width (from the focal-plane resolution, else a
  known camera model), else the 35 mm equivalent focal length. The last is a fallback only:
  cameras write the same 35 mm figure for 16:9 crops of a 4:3 sensor, and it then overstates
  the field of view by up to 10 %.

The camera's pose from a gimbal: the image top points along the gimbal yaw; pitch and roll are
the gimbal's tilt from nadir (pitch = gimbal pitch + 90, so a gimbal tilted forward is nose-up
in the localizer's convention: the view moves ahead).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.flightlog.autopilot import FlightLog, LoggedPoses

log = logging.getLogger(__name__)

PHOTO_SUFFIXES = (".jpg", ".jpeg")
_GPS_IFD, _EXIF_IFD = 0x8825, 0x8769
_GPS = {"lat_ref": 1, "lat": 2, "lon_ref": 3, "lon": 4, "alt_ref": 5, "alt": 6, "direction": 17}
_EXIF = {
    "time": 0x9003,
    "subsec": 0x9291,
    "offset": 0x9011,
    "focal": 0x920A,
    "focal_35": 0xA405,
    "plane_x_res": 0xA20E,
    "plane_unit": 0xA210,
    "exif_width": 0xA002,
}
_MODEL = 0x0110
_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}  # EXIF FocalPlaneResolutionUnit
_FULL_FRAME_DIAGONAL_MM = 43.27
# Sensor widths (mm) of common DJI cameras, from the makers' specifications (1/2.3" and 1").
SENSOR_WIDTH_MM = {
    "FC300S": 6.17,  # Phantom 3 Professional
    "FC300X": 6.17,  # Phantom 3 Advanced
    "FC330": 6.17,  # Phantom 4
    "FC220": 6.17,  # Mavic Pro
    "FC6310": 13.2,  # Phantom 4 Pro
    "FC6310S": 13.2,  # Phantom 4 Pro V2
    "L1D-20C": 13.2,  # Mavic 2 Pro
}
_XMP_PREFIX = b"http://ns.adobe.com/xap/1.0/\x00"
_DJI_TAG = re.compile(r'drone-dji:(\w+)\s*(?:=\s*"([^"]*)"|>([^<]*)<)')
_XMP_TAGS = {
    "rel_alt_m": "RelativeAltitude",
    "gimbal_yaw_deg": "GimbalYawDegree",
    "gimbal_pitch_deg": "GimbalPitchDegree",
    "gimbal_roll_deg": "GimbalRollDegree",
    "flight_yaw_deg": "FlightYawDegree",
}


@dataclass(frozen=True)
class Photo:
    """One geotagged photo; angles in degrees, None where the photo does not say."""

    path: Path
    time_s: float  # UNIX seconds (see the module docstring on time zones)
    lat: float
    lon: float
    alt_amsl_m: float | None
    rel_alt_m: float | None
    gimbal_yaw_deg: float | None
    gimbal_pitch_deg: float | None
    gimbal_roll_deg: float | None
    flight_yaw_deg: float | None
    camera: Camera | None
    has_xmp: bool

    @property
    def heading_deg(self) -> float | None:
        """Where the image top points: the gimbal's yaw, else the aircraft's."""
        return self.gimbal_yaw_deg if self.gimbal_yaw_deg is not None else self.flight_yaw_deg

    @property
    def tilt_deg(self) -> tuple[float | None, float | None]:
        """(pitch, roll) of the camera from nadir, or (None, None) without gimbal angles."""
        if self.gimbal_pitch_deg is None:
            return None, None
        return self.gimbal_pitch_deg + 90.0, self.gimbal_roll_deg or 0.0


@dataclass(frozen=True)
class PhotoFlight:
    """Photos sorted by capture time: the camera poses a log would give, at the photo times."""

    source: Path
    photos: tuple[Photo, ...]

    def __len__(self) -> int:
        return len(self.photos)

    @property
    def camera(self) -> Camera | None:
        """The photos' camera, if they all share one known camera."""
        cameras = {p.camera for p in self.photos}
        return cameras.pop() if len(cameras) == 1 else None

    def poses(self) -> LoggedPoses:
        """The camera pose of each photo (NaN where unknown), as a flight log gives them."""

        def column(values: Sequence[float | None]) -> np.ndarray:
            return np.array([math.nan if v is None else v for v in values], float)

        tilts = [p.tilt_deg for p in self.photos]
        return LoggedPoses(
            column([p.time_s for p in self.photos]),
            column([p.lat for p in self.photos]),
            column([p.lon for p in self.photos]),
            column([p.rel_alt_m for p in self.photos]),
            column([None if p.heading_deg is None else p.heading_deg % 360.0 for p in self.photos]),
            column([t[0] for t in tilts]),
            column([t[1] for t in tilts]),
        )

    def log(self) -> FlightLog:
        """The photos as a flight log, to interpolate poses between them (``log().at(times)``)."""
        poses = self.poses()
        if len(poses) < 2 or np.any(np.diff(poses.time_s) <= 0):
            raise OrthonavError(
                f"{self.source}: a flight log needs at least 2 photos with distinct capture times "
                "(EXIF times have a resolution of 1 s)"
            )
        return FlightLog(
            self.source,
            poses.time_s,
            poses.lat,
            poses.lon,
            poses.alt_agl_m,
            poses.time_s,
            poses.heading_deg,
            poses.pitch_deg,
            poses.roll_deg,
        )

    def at(self, times_s: np.ndarray) -> LoggedPoses:
        return self.log().at(times_s)


def read_photos(source: str | Path | Sequence[Path]) -> PhotoFlight:
    """A folder of JPEG photos (or a list of files) as a flight, sorted by capture time."""
    files, where = _photo_files(source)
    photos = sorted((read_photo(f) for f in files), key=lambda p: (p.time_s, p.path.name))
    without = [p.path.name for p in photos if not p.has_xmp]
    if without:
        log.warning(
            "%s: %d of %d photos have no DJI XMP (e.g. %s): their height above take-off and camera "
            "attitude are unknown; EXIF GPS and time only",
            where,
            len(without),
            len(photos),
            without[0],
        )
    return PhotoFlight(where, tuple(photos))


def _photo_files(source: str | Path | Sequence[Path]) -> tuple[list[Path], Path]:
    if isinstance(source, str | Path):
        folder = Path(source)
        if not folder.is_dir():
            raise OrthonavError(f"{folder}: no such photo folder")
        files = sorted(p for p in folder.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES and p.is_file())
        if not files:
            raise OrthonavError(f"{folder}: no JPEG photos ({', '.join(PHOTO_SUFFIXES)})")
        return files, folder
    files = [Path(p) for p in source]
    if not files:
        raise OrthonavError("photos: no files given")
    return files, files[0].parent


def read_photo(path: str | Path) -> Photo:
    """One photo's EXIF/XMP, or an error naming the file and the missing tag."""
    path = Path(path)
    if not path.is_file():
        raise OrthonavError(f"{path}: no such photo")
    try:
        with Image.open(path) as image:
            exif = image.getexif()
            gps, tags = exif.get_ifd(_GPS_IFD), exif.get_ifd(_EXIF_IFD)
            model = str(exif.get(_MODEL, "")).strip("\x00 ")
            size = image.size
            xmp = _dji_xmp(image, path)
    except (UnidentifiedImageError, OSError) as exc:
        raise OrthonavError(f"{path}: cannot be read as an image ({exc})") from None
    lat, lon = _gps_latlon(gps, path)
    values = {key: xmp.get(tag) for key, tag in _XMP_TAGS.items()}
    if values["gimbal_yaw_deg"] is None and values["flight_yaw_deg"] is None:
        values["gimbal_yaw_deg"] = _number(gps.get(_GPS["direction"]))
    return Photo(
        path,
        _capture_time(tags, path),
        lat,
        lon,
        _gps_altitude(gps),
        **values,
        camera=photo_camera(tags, model, *size),
        has_xmp=bool(xmp),
    )


def _number(value: Any) -> float | None:
    """An EXIF rational or number as a float; None when absent or not finite."""
    try:
        number = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return number if math.isfinite(number) else None


def _gps_latlon(gps: dict, path: Path) -> tuple[float, float]:
    lat, lon = _degrees(gps.get(_GPS["lat"])), _degrees(gps.get(_GPS["lon"]))
    if lat is None or lon is None:
        raise OrthonavError(
            f"{path}: no EXIF GPS position (GPSLatitude/GPSLongitude): not a geotagged photo, "
            "or its metadata was stripped"
        )
    lat = -lat if str(gps.get(_GPS["lat_ref"], "N")).upper().startswith("S") else lat
    lon = -lon if str(gps.get(_GPS["lon_ref"], "E")).upper().startswith("W") else lon
    if not (abs(lat) <= 90.0 and abs(lon) <= 180.0):
        raise OrthonavError(f"{path}: EXIF GPS position {lat}, {lon} is outside [-90, 90] / [-180, 180]")
    return lat, lon


def _degrees(dms: Any) -> float | None:
    """EXIF (degrees, minutes, seconds) rationals -> decimal degrees."""
    try:
        parts = [_number(v) for v in dms]
    except TypeError:
        return None
    if len(parts) != 3 or any(v is None for v in parts):
        return None
    return parts[0] + parts[1] / 60.0 + parts[2] / 3600.0


def _gps_altitude(gps: dict) -> float | None:
    alt = _number(gps.get(_GPS["alt"]))
    below = gps.get(_GPS["alt_ref"]) in (1, b"\x01")  # 1: below sea level
    return -alt if alt is not None and below else alt


def _capture_time(tags: dict, path: Path) -> float:
    text = str(tags.get(_EXIF["time"], "")).strip("\x00 ")
    try:
        stamp = datetime.strptime(text, "%Y:%m:%d %H:%M:%S")
    except ValueError:
        what = f"{text!r} is not 'YYYY:MM:DD HH:MM:SS'" if text else "missing"
        raise OrthonavError(f"{path}: EXIF DateTimeOriginal {what}: the capture time is unknown") from None
    subsec = str(tags.get(_EXIF["subsec"], "")).strip("\x00 ")
    fraction = float(f"0.{subsec}") if subsec.isdigit() else 0.0
    return (stamp.replace(tzinfo=_zone(tags.get(_EXIF["offset"]))).timestamp()) + fraction


def _zone(offset: Any) -> timezone:
    """EXIF OffsetTimeOriginal ('+02:00'); UTC when absent or unreadable."""
    match = re.fullmatch(r"([+-])(\d\d):(\d\d)", str(offset or "").strip("\x00 "))
    if not match:
        return UTC
    sign = -1 if match.group(1) == "-" else 1
    return timezone(sign * timedelta(hours=int(match.group(2)), minutes=int(match.group(3))))


def _dji_xmp(image: Image.Image, path: Path) -> dict[str, float]:
    """The numeric ``drone-dji:`` tags of the JPEG's XMP packet ({} without one)."""
    packets = [data for marker, data in getattr(image, "applist", []) if marker == "APP1"]
    xmp = next((d[len(_XMP_PREFIX) :] for d in packets if d.startswith(_XMP_PREFIX)), b"")
    found = {}
    for name, attribute, element in _DJI_TAG.findall(xmp.decode("utf-8", "replace")):
        text = attribute or element
        value = _number(text.strip())
        if value is None:
            raise OrthonavError(f"{path}: XMP drone-dji:{name} = {text!r} is not a number")
        found[name] = value
    return found


def photo_camera(tags: dict, model: str, width: int, height: int) -> Camera | None:
    """Pinhole intrinsics from EXIF (see the module docstring), or None if it does not say."""
    fx = _focal_px(tags, model, width, height)
    return None if fx is None else Camera(width, height, fx, fx, width / 2.0, height / 2.0)


def _focal_px(tags: dict, model: str, width: int, height: int) -> float | None:
    focal_mm = _number(tags.get(_EXIF["focal"]))
    if focal_mm and focal_mm > 0:
        px_per_mm = _focal_plane_px_per_mm(tags, width)
        if px_per_mm is None and model.upper() in SENSOR_WIDTH_MM:
            px_per_mm = width / SENSOR_WIDTH_MM[model.upper()]
        if px_per_mm is not None:
            return focal_mm * px_per_mm
    focal_35 = _number(tags.get(_EXIF["focal_35"]))
    if focal_35 and focal_35 > 0:
        return focal_35 * math.hypot(width, height) / _FULL_FRAME_DIAGONAL_MM
    return None


def _focal_plane_px_per_mm(tags: dict, width: int) -> float | None:
    """Pixels per mm on the sensor at this image's width, from the focal-plane resolution."""
    resolution = _number(tags.get(_EXIF["plane_x_res"]))
    unit_mm = _PLANE_UNIT_MM.get(int(_number(tags.get(_EXIF["plane_unit"])) or 2))
    if not resolution or resolution <= 0 or unit_mm is None:
        return None
    exif_width = _number(tags.get(_EXIF["exif_width"])) or width
    return resolution / unit_mm * width / exif_width
