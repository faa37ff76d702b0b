"""What goes into and comes out of a localizer: ``Prior`` in, ``Fix`` out."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Protocol

import numpy as np

from orthonav.camera import Camera, CameraPose, footprint_enu
from orthonav.errors import OrthonavError, require_positive
from orthonav.geo import LocalFrame, check_latlon

MAX_ALT_AGL_M = 20_000.0
# An attitude known no better than this places the point below the camera no better than a third
# of the height (tan 20 deg): a frame captured while the vehicle turns faster than its attitude
# samples follow is not placed at all, rather than with a sigma of kilometres.
MAX_ATTITUDE_SIGMA_DEG = 20.0


@dataclass(frozen=True)
class Prior:
    """What the vehicle believes before the fix; every field may be unknown (None)."""

    lat: float | None = None
    lon: float | None = None
    alt_agl_m: float | None = None
    heading_deg: float | None = None
    pitch_deg: float | None = None
    roll_deg: float | None = None
    sigma_m: float = 200.0
    heading_sigma_deg: float = 10.0
    # Roll/pitch from a flight controller's EKF are good to a few tenths of a degree in steady flight.
    attitude_sigma_deg: float = 0.3

    def __post_init__(self) -> None:
        if (self.lat is None) != (self.lon is None):
            raise OrthonavError("prior: give both latitude and longitude, or neither")
        if self.lat is not None:
            check_latlon(self.lat, self.lon, "prior")
        if self.alt_agl_m is not None and not (
            math.isfinite(self.alt_agl_m) and 1.0 <= self.alt_agl_m <= MAX_ALT_AGL_M
        ):
            raise OrthonavError(
                f"prior altitude: expected 1..{MAX_ALT_AGL_M:.0f} m above ground, got {self.alt_agl_m}"
            )
        if self.heading_deg is not None and not (
            math.isfinite(self.heading_deg) and -360.0 <= self.heading_deg <= 360.0
        ):
            raise OrthonavError(
                f"prior heading: expected an angle in -360..360 degrees from north, got {self.heading_deg}"
            )
        if (self.pitch_deg is None) != (self.roll_deg is None):
            raise OrthonavError("prior: give both pitch and roll, or neither")
        if self.pitch_deg is not None and not (abs(self.pitch_deg) < 60 and abs(self.roll_deg) < 60):
            raise OrthonavError(
                f"prior pitch/roll {self.pitch_deg}, {self.roll_deg}: expected finite angles within +-60 deg"
            )
        require_positive("prior", self, ("sigma_m", "heading_sigma_deg", "attitude_sigma_deg"))
        if not self.attitude_sigma_deg <= MAX_ATTITUDE_SIGMA_DEG:
            raise OrthonavError(
                f"prior attitude sigma {self.attitude_sigma_deg:.1f} deg: expected at most "
                f"{MAX_ATTITUDE_SIGMA_DEG:.0f} deg (an attitude changing faster than its samples follow)"
            )

    @property
    def has_position(self) -> bool:
        return self.lat is not None

    @property
    def has_attitude(self) -> bool:
        return self.pitch_deg is not None


@dataclass(frozen=True)
class Pose:
    """The vehicle's pose from one frame: the point under the camera, and where it looks."""

    lat: float
    lon: float
    alt_agl_m: float
    heading_deg: float
    pitch_deg: float
    roll_deg: float
    centre_lat: float
    centre_lon: float

    def footprint_latlon(self, camera: Camera) -> np.ndarray:
        """(4, 2) WGS84 (lat, lon) of the image corners on the ground: TL, TR, BR, BL."""
        return footprint_latlon(
            camera, self.lat, self.lon, self.alt_agl_m, self.heading_deg, self.pitch_deg, self.roll_deg
        )


def positive_definite(covariance: np.ndarray) -> bool:
    """Whether a covariance can weigh a measurement: its symmetric part (rounding leaves a
    computed one slightly asymmetric) has no eigenvalue at or below zero."""
    return bool(min(np.linalg.eigvalsh((covariance + covariance.T) / 2.0)) > 0.0)


def worst_sigma(covariance: np.ndarray) -> float:
    """The 1-sigma of a covariance along its worst direction (its largest eigenvalue's root): one
    number that must hold whichever way the error lies. A rounding error's negative eigenvalue of
    a zero covariance is a zero sigma, not a math error."""
    return float(math.sqrt(max(0.0, *np.linalg.eigvalsh(covariance))))


def footprint_latlon(
    camera: Camera,
    lat: float,
    lon: float,
    alt_agl_m: float,
    heading_deg: float,
    pitch_deg: float,
    roll_deg: float,
) -> np.ndarray:
    """(4, 2) WGS84 (lat, lon) of the image corners on the ground seen from a vehicle pose."""
    corners = footprint_enu(camera, CameraPose(0.0, 0.0, alt_agl_m, heading_deg, pitch_deg, roll_deg))
    clat, clon = LocalFrame(lat, lon).to_latlon(corners[:, 0], corners[:, 1])
    return np.column_stack([clat, clon])


def unpinned(quality: dict[str, float]) -> bool:
    """A pose its source says no keypoint inliers pin (``inliers`` 0: a correlation pose). Right
    where a prior narrows the search; where nothing does, ground that repeats can hold a twin
    place hundreds of metres away that a correlation fits as well or better, with a margin over
    its own neighbourhood and a sure acceptance, and frame after frame agrees on it."""
    return "inliers" in quality and not quality["inliers"]


@dataclass
class Fix:
    """One localization result: an accepted pose with covariance, or a rejection with reason.

    ``covariance_enu_m2`` is the 2x2 horizontal position covariance (east, north) in m^2.
    ``inliers_frame_px`` and ``inliers_map_px`` are the (N, 2) point pairs the fix's homography
    kept, accepted or not: frame pixels (OpenCV convention, pixel centres at integers) and
    work-grid pixels of the map package. They are for pictures of the match (a sample of a
    few hundred at most, never in ``to_dict``); None where the source has no point matches.
    """

    accepted: bool
    reason: str = ""
    pose: Pose | None = None
    covariance_enu_m2: np.ndarray | None = None
    quality: dict[str, float] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)
    method: str = ""
    inliers_frame_px: np.ndarray | None = field(default=None, repr=False)
    inliers_map_px: np.ndarray | None = field(default=None, repr=False)

    @property
    def sigma_m(self) -> float | None:
        """1-sigma of the worst horizontal direction."""
        if self.covariance_enu_m2 is None:
            return None
        return worst_sigma(self.covariance_enu_m2)

    @property
    def unpinned(self) -> bool:
        """Whether nothing in the fix pins its place by itself (:func:`unpinned`)."""
        return unpinned(self.quality)

    def to_dict(self) -> dict:
        """Flat JSON-ready record (the ``--json`` / ``fixes.jsonl`` format).

        A rejected fix has no position fields, so nothing downstream can mistake it for one;
        the pose it was rejected with, if any, is kept apart under ``rejected_pose``.
        """
        pose = asdict(self.pose) if self.pose and self.accepted else {}
        cov = self.covariance_enu_m2
        extra = {"rejected_pose": asdict(self.pose)} if self.pose and not self.accepted else {}
        return {
            "accepted": self.accepted,
            "reason": self.reason,
            "lat": pose.get("lat"),
            "lon": pose.get("lon"),
            "altitude": pose.get("alt_agl_m"),
            "heading": pose.get("heading_deg"),
            "pitch": pose.get("pitch_deg"),
            "roll": pose.get("roll_deg"),
            "centre_lat": pose.get("centre_lat"),
            "centre_lon": pose.get("centre_lon"),
            "covariance": None if cov is None else np.round(cov, 3).tolist(),
            "sigma_m": None if cov is None else round(self.sigma_m, 3),
            "inliers": int(self.quality.get("inliers", 0)),
            "rmse": self.quality.get("rmse_px"),
            "quality": {k: _round(v) for k, v in self.quality.items()},
            "timings": {k: round(v, 2) for k, v in self.timings_ms.items()},
            "method": self.method,
            **extra,
        }

    @classmethod
    def from_dict(cls, data: dict) -> Fix:
        """A fix read back from its :meth:`to_dict` record (e.g. a companion log), as rounded there;
        the inlier pairs are not in the record."""
        try:
            if data["accepted"]:
                keys = ("lat", "lon", "altitude", "heading", "pitch", "roll", "centre_lat", "centre_lon")
                pose = Pose(*(float(data[key]) for key in keys))
            elif data.get("rejected_pose"):
                pose = Pose(**{key: float(value) for key, value in data["rejected_pose"].items()})
            else:
                pose = None
            cov = data.get("covariance")
            return cls(
                bool(data["accepted"]),
                str(data.get("reason") or ""),
                pose,
                None if cov is None else np.asarray(cov, dtype=float).reshape(2, 2),
                {key: float(value) for key, value in (data.get("quality") or {}).items()},
                {key: float(value) for key, value in (data.get("timings") or {}).items()},
                str(data.get("method") or ""),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise OrthonavError(
                f"fix record: expected the fields of Fix.to_dict, {type(exc).__name__}: {exc}"
            ) from None


def _round(value: float) -> float:
    return round(float(value), 4)


class FixSource(Protocol):
    """Frame + prior -> ``Fix``: the keypoint :class:`Localizer` and the dense-correlation
    ``Corrector`` alike, so the mission and companion loops (and the filter) take either."""

    def localize(self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix: ...
