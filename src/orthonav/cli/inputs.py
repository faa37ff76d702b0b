"""Reading the CLI's inputs: the priors CSV, frame folders, weight-file lists.

Priors CSV (one row per frame file; empty cell = unknown; column names are case-insensitive)::

    name,lat,lon,altitude,heading[,pitch,roll,sigma_m]
    frame_0001.jpg,47.0203,-99.1548,1000,45.0

Common spellings are accepted: ``latitude``, ``longitude``/``lng``, ``alt``, ``yaw``. Given
the frames being localized, :func:`read_priors` says which rows matched them, warns about rows
naming no frame and repeated names, and refuses a file that matches none.
"""

from __future__ import annotations

import csv
import logging
import math
from collections.abc import Sequence
from pathlib import Path

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import weight_keys
from orthonav.geo import check_latlon
from orthonav.localize.sources import FIX_SOURCES
from orthonav.types import Prior

log = logging.getLogger(__name__)

# The benchmarks' default inputs: the project's shared data beside the checkout, relative to where
# the command runs (the project root), as the CLI reference says; never beside this file, which
# after `pip install .` lies inside the environment.
SHARED_DATA = Path("..") / "shared" / "data"
WEIGHTS_HELP = "Weight files for backends that take them (superpoint: SUPERPOINT.pth,SUPERGLUE.pth)."
DEVICE_HELP = "Where learned backends run: cpu, cuda or cuda:N."
THREADS_HELP = "Torch CPU threads for learned backends (default: torch's choice)."
TRUNK_CHECK_HELP = (
    "A second check of each proposed position: how well the features of orthonav's trained CNN (a "
    "ResNet-18 fitted on aerial photos of several dates) agree between frame and map. auto (where the CNN "
    "loads and the map's pixels are 1 m or coarser, measured for the proposals the decision is not "
    "sure of without it: more fixes across dates), on (measured for every proposal; an error where "
    "the CNN does not load), off (never: about 40 ms less on the frames that measure it)."
)

PRIOR_FIELDS = ("lat", "lon", "altitude", "heading", "pitch", "roll", "sigma_m")
# Column names accepted for each field, lower case; the first is the documented one.
PRIOR_COLUMNS = {
    "lat": ("lat", "latitude"),
    "lon": ("lon", "longitude", "lng"),
    "altitude": ("altitude", "alt"),
    "heading": ("heading", "yaw"),
    "pitch": ("pitch",),
    "roll": ("roll",),
    "sigma_m": ("sigma_m",),
}
NAMES_SHOWN = 10  # rows named in one warning; the rest are counted


def read_priors(path: Path, frames: Sequence[str | Path] | None = None) -> dict[str, Prior]:
    """Priors by frame file name; every problem names the file, line and field.

    With ``frames`` (the frame files being localized) only the rows naming one of them are
    returned, keyed by the frame's file name (a row may give a path: its file name counts); the
    matches are logged, rows naming no frame and repeated names are warned about (the last row
    of a name is used: a CSV appended to by a re-run says the newest), and a file matching no
    frame at all is an error, since every frame would silently go without its prior.
    """
    header, rows = _read_csv(path)
    columns = _prior_columns(path, header)
    priors: dict[str, Prior] = {}
    lines: dict[str, list[int]] = {}
    for line, row in enumerate(rows, start=2):
        name = (row.get(columns["name"]) or "").strip()
        if not name:
            log.warning("%s:%d: no frame name: row ignored", path, line)
            continue
        priors[name] = _prior(path, line, row, columns)
        lines.setdefault(name, []).append(line)
    _warn_repeated(path, lines)
    if frames is None:
        return priors
    return _match_frames(path, priors, lines, [Path(frame).name for frame in frames])


def _read_csv(path: Path) -> tuple[list[str], list[dict[str | None, str | None]]]:
    """(header, rows); an error naming the file when it is missing, unreadable or has no rows."""
    try:
        # utf-8-sig: spreadsheets (Excel's "CSV UTF-8") start the file with a byte order mark.
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.DictReader(fh)
            rows = list(reader)
            header = list(reader.fieldnames or [])
    except FileNotFoundError:
        raise OrthonavError(f"{path}: no such priors file") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise OrthonavError(f"{path}: not a readable CSV file ({exc})") from None
    if header and not rows:
        raise OrthonavError(f"{path}: a header and no rows: no priors in it")
    return header, rows


def _prior_columns(path: Path, header: list[str]) -> dict[str, str | None]:
    """The column giving ``name`` and each prior field (None: absent); unknown columns warned about."""
    by_key = {column.strip().lower(): column for column in header if column is not None}
    if len(by_key) < len(header):
        raise OrthonavError(f"{path}: a column name appears twice in the header {header}")
    if "name" not in by_key:
        raise OrthonavError(f"{path}: expected a header with 'name' and {', '.join(PRIOR_FIELDS)}")
    columns: dict[str, str | None] = {"name": by_key["name"]}
    for field, spellings in PRIOR_COLUMNS.items():
        present = [by_key[key] for key in spellings if key in by_key]
        if len(present) > 1:
            raise OrthonavError(
                f"{path}: columns {' and '.join(map(repr, present))} both give {field}: keep one"
            )
        columns[field] = present[0] if present else None
    known = {"name", *(key for spellings in PRIOR_COLUMNS.values() for key in spellings)}
    unknown = [column for key, column in by_key.items() if key not in known]
    if unknown:
        accepted = ", ".join("/".join(spellings) for spellings in PRIOR_COLUMNS.values())
        log.warning(
            "%s: columns ignored: %s (prior columns: name, %s)", path, ", ".join(map(repr, unknown)), accepted
        )
    return columns


def _prior(path: Path, line: int, row: dict[str | None, str | None], columns: dict[str, str | None]) -> Prior:
    values: dict[str, float | None] = {}
    for field in PRIOR_FIELDS:
        column = columns[field]
        values[field] = _number(row.get(column), path, line, column) if column else None
    try:
        return Prior(
            lat=values["lat"],
            lon=values["lon"],
            alt_agl_m=values["altitude"],
            heading_deg=values["heading"],
            pitch_deg=values["pitch"],
            roll_deg=values["roll"],
            sigma_m=Prior.sigma_m if values["sigma_m"] is None else values["sigma_m"],
        )
    except OrthonavError as exc:
        raise OrthonavError(f"{path}:{line}: {exc}") from None


def _warn_repeated(path: Path, lines: dict[str, list[int]]) -> None:
    repeated = [f"{name!r} (lines {', '.join(map(str, at))})" for name, at in lines.items() if len(at) > 1]
    if repeated:
        log.warning(
            "%s: %d frame names repeated, the last row of each is used: %s",
            path,
            len(repeated),
            _some(repeated),
        )


def _match_frames(
    path: Path, priors: dict[str, Prior], lines: dict[str, list[int]], frames: list[str]
) -> dict[str, Prior]:
    """The priors of ``frames`` by frame name; unmatched rows warned about, no match refused."""
    wanted = set(frames)
    matched: dict[str, Prior] = {}
    unmatched: list[str] = []
    for name, prior in priors.items():
        frame = name if name in wanted else Path(name).name
        if frame in wanted:
            matched[frame] = prior
        else:
            unmatched.append(f"line {lines[name][-1]} {name!r}")
    if not matched:
        example = (
            f" (rows name e.g. {next(iter(priors))!r}, frames e.g. {frames[0]!r})"
            if priors and frames
            else ""
        )
        raise OrthonavError(f"{path}: no row names a frame being localized{example}")
    if unmatched:
        log.warning("%s: %d rows name no frame being localized: %s", path, len(unmatched), _some(unmatched))
    log.info("%s: priors for %d of %d frames: %s", path, len(matched), len(frames), _some(list(matched)))
    return matched


def _some(items: list[str]) -> str:
    """The first few items, and how many more."""
    shown = ", ".join(items[:NAMES_SHOWN])
    return shown + (f" and {len(items) - NAMES_SHOWN} more" if len(items) > NAMES_SHOWN else "")


def _number(text: str | None, path: Path, line: int, key: str) -> float | None:
    if text is None or not text.strip():
        return None
    try:
        value = float(text)
    except ValueError:
        raise OrthonavError(f"{path}:{line}: field {key!r} = {text!r} is not a number") from None
    if not math.isfinite(value):
        raise OrthonavError(f"{path}:{line}: field {key!r} = {text!r} must be finite")
    return value


def parse_latlon(text: str, option: str) -> tuple[float, float]:
    """'LAT,LON' -> (lat, lon), with a clear error naming the option."""
    parts = text.split(",")
    try:
        lat, lon = (float(p) for p in parts)
    except ValueError:
        raise OrthonavError(f"{option}: expected LAT,LON in degrees, got {text!r}") from None
    check_latlon(lat, lon, option)
    return lat, lon


def weights_conf(backend: str, weights: str | None) -> dict[str, str]:
    """``--weights a.pth[,b.pth]`` as the backend's weight-file config keys, in its order."""
    if not weights:
        return {}
    keys = weight_keys(backend)
    files = [w.strip() for w in weights.split(",") if w.strip()]
    if not keys:
        raise OrthonavError(f"--weights: the {backend!r} backend ships its own weights and takes none")
    if len(files) != len(keys):
        raise OrthonavError(
            f"--weights: {backend} takes {len(keys)} comma-separated file(s) ({', '.join(keys)}), "
            f"got {len(files)}"
        )
    for file in files:
        if not Path(file).is_file():
            raise OrthonavError(f"--weights: {file}: no such file")
    return {key: str(Path(file).resolve()) for key, file in zip(keys, files, strict=True)}


def parse_length_m(text: str, option: str) -> float:
    """``2km``, ``500m`` or ``500`` (metres) -> metres > 0."""
    value = text.strip().lower()
    factor = 1000.0 if value.endswith("km") else 1.0
    try:
        metres = float(value.removesuffix("km").removesuffix("m")) * factor
    except ValueError:
        raise OrthonavError(f"{option} {text!r}: expected a length such as 2km, 500m or 500") from None
    if not (math.isfinite(metres) and metres > 0):
        raise OrthonavError(f"{option} {text!r}: expected a positive length")
    return metres


def parse_area(text: str, option: str) -> tuple[float, float]:
    """``START,END`` shares of a map's width (0..1), e.g. ``0,0.5``."""
    try:
        start, end = (float(v) for v in text.split(","))
    except ValueError:
        raise OrthonavError(
            f"{option} {text!r}: expected START,END shares of the map width, e.g. 0,0.5"
        ) from None
    if not 0.0 <= start < end <= 1.0:
        raise OrthonavError(f"{option} {text!r}: expected 0 <= START < END <= 1")
    return start, end


def camera_from_options(camera_json: Path | None, width: int, height: int, hfov: float) -> Camera:
    """The camera from a JSON file, or a pinhole of the given size and horizontal field of view."""
    return Camera.from_json(camera_json) if camera_json else Camera.from_hfov(width, height, hfov)


FIX_SOURCE_HELP = (
    f"{' | '.join(FIX_SOURCES)}: the cascade (dense correlation with the map's orthophoto, the "
    "map's keypoints near it, verification, a calibrated acceptance: right across dates; needs the "
    "altitude), the map's keypoints alone (fast on frames of the map's own date), or dense gradient "
    "correlation alone (needs position, altitude and heading). Default: the cascade where the map's "
    "orthophoto (recorded in its manifest) is there, else keypoints, saying why."
)
FALLBACK_HELP = (
    "Another map package of the same area, built with another backend, asked where this map's fix "
    "is rejected (e.g. an ALIKED map behind an ORB one: ORB's time on most frames, ALIKED's fixes "
    "on the rest). Repeat for more, in order."
)
# ``--trunk-check`` by name: CascadeConfig.trunk_check's values.
TRUNK_CHECKS: dict[str, bool | None] = {"auto": None, "on": True, "off": False}


def fix_source_option(value: str | None) -> str | None:
    """``--fix-source``, checked by name; None: the default (see FIX_SOURCE_HELP)."""
    if value is not None and value not in FIX_SOURCES:
        raise OrthonavError(f"--fix-source {value!r}: expected one of {', '.join(FIX_SOURCES)}")
    return value


def trunk_check_option(value: str) -> bool | None:
    """``--trunk-check`` (auto, on, off) as :attr:`CascadeConfig.trunk_check`."""
    if value not in TRUNK_CHECKS:
        raise OrthonavError(f"--trunk-check {value!r}: expected one of {', '.join(TRUNK_CHECKS)}")
    return TRUNK_CHECKS[value]
