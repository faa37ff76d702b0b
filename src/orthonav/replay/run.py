"""Replay a recorded flight through the localizer and score it against the recorded GNSS.

Each frame gets the prior an autopilot would have given at its time: altitude above
home/take-off, heading, pitch and roll from the log, and the logged position with
``prior_sigma_m`` (or no position: every map tile is searched). The logged GNSS position is
the reference: ``error_m`` is the geodesic distance from it to the fix. It is GNSS, not truth:
a few metres of it are the receiver's, and the frame sync (time offset) adds speed x offset error.

Writes into ``out_dir``: ``config.json`` first, ``replay.jsonl`` line by line (flushed, so an
interrupted replay keeps every frame done), then ``summary.json`` and ``replay.png``.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orthonav.atomic import open_output, write_json_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.flightlog import LoggedPoses
from orthonav.flightlog.photos import PhotoFlight
from orthonav.frames import FrameSource, Unreadable, check_frame_size
from orthonav.geo import distance_m
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage
from orthonav.replay.inputs import ReplayInput, flight_input, photo_input
from orthonav.types import Fix, Prior

log = logging.getLogger(__name__)

RECORDS, SUMMARY, CONFIG, PLOT = "replay.jsonl", "summary.json", "config.json", "replay.png"


@dataclass(frozen=True)
class ReplayConfig:
    """How the recorded flight becomes priors; ``prior_sigma_m=None``: no position prior."""

    every: int = 1
    prior_sigma_m: float | None = 50.0
    heading_sigma_deg: float = 10.0
    attitude_sigma_deg: float = 0.3
    nadir_gimbal: bool = False  # the camera hangs in a gimbal: the vehicle's pitch/roll are not its own

    def __post_init__(self) -> None:
        if self.prior_sigma_m is not None and not (
            math.isfinite(self.prior_sigma_m) and self.prior_sigma_m > 0
        ):
            raise OrthonavError(f"prior sigma: expected metres > 0 (or none), got {self.prior_sigma_m}")


@dataclass(frozen=True)
class ReplayResult:
    out_dir: Path
    records: list[dict]
    summary: dict


def replay_flight(
    log_path: Path,
    frames: FrameSource,
    offset_s: float,
    localizer: Localizer,
    out_dir: Path,
    config: ReplayConfig | None = None,
) -> ReplayResult:
    """A flight log with its video or image folder; frame 0 at log time ``offset_s``."""
    config = config or ReplayConfig()
    return run_replay(flight_input(log_path, frames, offset_s, config.every), localizer, out_dir, config)


def replay_photos(
    flight: PhotoFlight, localizer: Localizer, out_dir: Path, config: ReplayConfig | None = None
) -> ReplayResult:
    """Geotagged photos (:func:`camera_for_photos` gives the camera for their localizer)."""
    config = config or ReplayConfig()
    return run_replay(photo_input(flight, config.every), localizer, out_dir, config)


def camera_for_photos(flight: PhotoFlight, camera: Camera | None) -> Camera:
    """The camera given, else the one the photos' EXIF describes."""
    camera = camera or flight.camera
    if camera is None:
        raise OrthonavError(
            f"{flight.source}: the photos' EXIF gives no focal length, or they differ: give the camera"
        )
    return camera


def run_replay(
    source: ReplayInput, localizer: Localizer, out_dir: Path, config: ReplayConfig
) -> ReplayResult:
    """Localize every frame of ``source`` taken over the map; write and return the records."""
    package = localizer.package
    on_map = _on_map(package, source.poses, source.name)
    skipped = {**source.skipped, "off the map": int((~on_map).sum())}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_dir / CONFIG, _config_record(source, localizer, config))
    indices = np.flatnonzero(on_map).tolist()
    records = _localize_all(source, indices, localizer, config, out_dir / RECORDS)
    if len(records) < len(indices):
        skipped["not in the frames"] = len(indices) - len(records)
        log.warning(
            "%s: the frames end early: %d frames the log covers are missing",
            source.name,
            skipped["not in the frames"],
        )
    summary = summarize(records, skipped)
    write_json_atomic(out_dir / SUMMARY, summary)
    if records:
        from orthonav.viz.replay import plot_replay

        plot_replay(package, records, out_dir / PLOT, _title(source.name, summary))
    return ReplayResult(out_dir, records, summary)


def _localize_all(
    source: ReplayInput, indices: list[int], localizer: Localizer, config: ReplayConfig, path: Path
) -> list[dict]:
    """One record per frame read, each written and flushed as soon as it is made."""
    records = []
    frames = tqdm(
        zip(indices, source.read(indices), strict=False),
        total=len(indices),
        unit="frame",
        desc="replay",
        disable=None,  # shown on a terminal, silent in logs and tests
    )
    with open_output(path) as sink, frames:
        for k, (label, image) in frames:
            if not isinstance(image, Unreadable):
                check_frame_size(image, localizer.camera, label)
            record = _localize(localizer, image, source.poses, k, config, label)
            sink.write(json.dumps(record) + "\n")
            sink.flush()
            records.append(record)
    return records


def _on_map(package: MapPackage, poses: LoggedPoses, name: str) -> np.ndarray:
    """Which recorded positions lie on the map; an error if none does, a warning if some do not."""
    inside = np.array(
        [package.grid.contains_latlon(lat, lon) for lat, lon in zip(poses.lat, poses.lon, strict=True)]
    )
    if not inside.any():
        raise OrthonavError(
            f"{name}: none of its {len(poses)} frames was taken over the map {package.path}: the flight "
            f"is {package.away(poses.lat, poses.lon)}"
        )
    if not inside.all():
        log.warning(
            "%s: %d of %d frames were taken off the map: skipped", name, int((~inside).sum()), len(poses)
        )
    return inside


def _localize(
    localizer: Localizer,
    image: np.ndarray | Unreadable,
    poses: LoggedPoses,
    k: int,
    config: ReplayConfig,
    label: str,
) -> dict:
    logged = {
        "lat": poses.lat[k],
        "lon": poses.lon[k],
        "alt_agl_m": poses.alt_agl_m[k],
        "heading_deg": poses.heading_deg[k],
        "pitch_deg": poses.pitch_deg[k],
        "roll_deg": poses.roll_deg[k],
    }
    logged = {key: _finite(value) for key, value in logged.items()}
    try:
        prior = _prior(logged, config)
    except OrthonavError as exc:  # a logged value no prior can take (e.g. 70 deg of roll)
        fix = Fix(False, f"prior from the log: {exc}")
    else:
        fix = Fix(False, image.reason) if isinstance(image, Unreadable) else localizer.localize(image, prior)
    error = distance_m(logged["lat"], logged["lon"], fix.pose.lat, fix.pose.lon) if fix.accepted else None
    return {
        "frame": label,
        "time_s": float(poses.time_s[k]),
        **{f"log_{key}": value for key, value in logged.items()},
        "fix": fix.to_dict(),
        "error_m": None if error is None else round(float(error), 3),
    }


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _prior(logged: dict, config: ReplayConfig) -> Prior:
    """The prior the autopilot gave at the frame's time; below 1 m the vehicle is on the ground."""
    alt = logged["alt_agl_m"] if (logged["alt_agl_m"] or 0.0) >= 1.0 else None
    tilt = (logged["pitch_deg"], logged["roll_deg"])
    if config.nadir_gimbal or None in tilt:
        tilt = (None, None)
    position = (logged["lat"], logged["lon"]) if config.prior_sigma_m is not None else (None, None)
    return Prior(
        *position,
        alt,
        logged["heading_deg"],
        *tilt,
        sigma_m=config.prior_sigma_m or Prior.sigma_m,
        heading_sigma_deg=config.heading_sigma_deg,
        attitude_sigma_deg=config.attitude_sigma_deg,
    )


def error_stats(values: list[float], digits: int = 3) -> dict | None:
    """Mean, median, 95th percentile and max of errors (m); None when there are none."""
    if not values:
        return None
    errors = np.asarray(values, float)
    stats = {
        "mean": errors.mean(),
        "median": np.median(errors),
        "p95": np.percentile(errors, 95),
        "max": errors.max(),
    }
    return {key: round(float(value), digits) for key, value in stats.items()}


def summarize(records: list[dict], skipped: dict[str, int]) -> dict:
    """Fix rate over the frames localized, error statistics over the fixes (m)."""
    errors = [r["error_m"] for r in records if r["error_m"] is not None]
    return {
        "frames": len(records),
        "fixes": len(errors),
        "fix_rate": round(len(errors) / len(records), 4) if records else 0.0,
        "error_m": error_stats(errors),
        "skipped": skipped,
    }


def _config_record(source: ReplayInput, localizer: Localizer, config: ReplayConfig) -> dict:
    return {
        "source": source.info,
        "map": str(localizer.package.path),
        "features": localizer.package.backend_name,
        "camera": localizer.camera.to_dict(),
        "replay": asdict(config),
        "localizer": localizer.config.to_dict(),
    }


def _title(name: str, summary: dict) -> str:
    stats = summary["error_m"]
    error = f", median error {stats['median']:.1f} m" if stats else ""
    return f"replay {name}: {summary['fixes']} of {summary['frames']} frames fixed{error}"
