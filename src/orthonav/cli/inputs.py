"""Reading the CLI's inputs: the priors CSV, frame folders, weight-file lists.

Priors CSV (one row per frame file; empty cell = unknown)::

    name,lat,lon,altitude,heading[,pitch,roll,sigma_m]
    frame_0001.jpg,47.0203,-99.1548,1000,45.0
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import weight_keys
from orthonav.geo import check_latlon
from orthonav.types import Prior

# The project's shared data beside a source checkout: the benchmarks' default inputs.
SHARED_DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"
WEIGHTS_HELP = "Weight files for backends that take them (superpoint: SUPERPOINT.pth,SUPERGLUE.pth)."
DEVICE_HELP = "Where learned backends run: cpu, cuda or cuda:N."
THREADS_HELP = "Torch CPU threads for learned backends (default: torch's choice)."

PRIOR_FIELDS = ("lat", "lon", "altitude", "heading", "pitch", "roll", "sigma_m")


def read_priors(path: Path) -> dict[str, Prior]:
    """Priors by frame file name; every problem names the file, line and field."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
            header = rows[0].keys() if rows else []
    except FileNotFoundError:
        raise OrthonavError(f"{path}: no such priors file") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise OrthonavError(f"{path}: not a readable CSV file ({exc})") from None
    if "name" not in header:
        raise OrthonavError(f"{path}: expected a header with 'name' and {', '.join(PRIOR_FIELDS)}")
    priors = {}
    for line, row in enumerate(rows, start=2):
        values = {key: _number(row.get(key), path, line, key) for key in PRIOR_FIELDS}
        try:
            prior = Prior(
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
        priors[row["name"]] = prior
    return priors


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
