"""The vehicle's ground velocity from consecutive frames of a level (gimbal-held nadir) camera.

Why a similarity fit and not the full homography of :mod:`orthonav.odometry.motion`: at cruise
height a small tilt between two frames and a horizontal displacement move the image almost alike,
and the homography trades one for the other with the matches' noise. A gimbal holds the camera
level, so the ground's image between two frames is a rotation, a scale (climb) and a shift; the
shift of the image centre times the ground sample distance is the displacement, rotated to
east/north with the heading. That is a velocity measured against the ground, independent of the
autopilot's, which the navigation filter fuses and the autopilot can weigh.

The covariance is what the fit can tell, widened for what it cannot: twice the standard error of
the inliers' shift (the inliers of one frame pair are not independent), a pixel-noise floor, the
gimbal's residual jitter between frames (at height, a hundredth of a degree moves the image
centre by decimetres), the heading's uncertainty across the displacement and the height's along
it. A pair that fits too few inliers, too small a share of the matches, or a scale or turn no
vehicle makes between two frames raises :class:`VelocityError`: nothing is measured.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet, backend_class, create_backend
from orthonav.types import worst_sigma

# The heading walk (FilterConfig.heading_walk_deg_per_sqrt_s) of a filter that fuses these
# velocities turned with an autopilot's heading: its yaw can step by degrees when its aiding
# changes, and the fixes' headings must tell the filter within seconds, not as slowly as an IMU
# drifts, or the velocities hand the step back to it.
HEADING_WALK_DEG_PER_SQRT_S = 0.3


def heading_walk_for(fuses_frame_velocity: bool) -> float:
    """The heading walk of a filter: HEADING_WALK_DEG_PER_SQRT_S where it fuses these velocities;
    without them its heading only drifts as the IMU's does."""
    return HEADING_WALK_DEG_PER_SQRT_S if fuses_frame_velocity else 0.0


class VelocityError(OrthonavError):
    """Two frames give no trustworthy ground velocity."""


@dataclass(frozen=True)
class VelocityConfig:
    """Thresholds and error terms of :class:`FrameVelocity`."""

    max_keypoints: int = 1000
    ransac_px: float = 2.0
    min_inliers: int = 100
    min_inlier_ratio: float = 0.3
    max_gap_s: float = 1.5  # frames further apart than this give no velocity (a restart)
    max_scale_change: float = 0.1  # image scale between two frames: a climb of a tenth of the height
    max_turn_deg: float = 45.0
    fit_sigmas: float = 3.0  # the shift's standard error times this
    floor_px: float = 0.1  # pixel noise the fit's own spread does not show (JPEG, resampling)
    tilt_jitter_deg: float = 0.02  # a stabilised gimbal's angular vibration, frame to frame
    heading_sigma_deg: float = 2.0  # the autopilot's heading error, beyond what it reports
    height_sigma_frac: float = 0.03  # height above the ground (the scale), as a fraction


@dataclass(frozen=True)
class GroundVelocity:
    """Mean ground velocity between two captures, at their mid-time, in east/north m/s."""

    time_s: float
    east_mps: float
    north_mps: float
    covariance_m2ps2: np.ndarray  # 2x2, east/north
    inliers: int
    baseline_s: float

    @property
    def sigma_mps(self) -> float:
        """1-sigma of the worst direction."""
        return worst_sigma(self.covariance_m2ps2)

    def to_dict(self) -> dict:
        return {
            "time_s": round(self.time_s, 6),
            "east_mps": round(self.east_mps, 3),
            "north_mps": round(self.north_mps, 3),
            "covariance_m2ps2": np.round(self.covariance_m2ps2, 5).tolist(),
            "sigma_mps": round(self.sigma_mps, 3),
            "inliers": self.inliers,
            "baseline_s": round(self.baseline_s, 3),
        }

    @classmethod
    def from_dict(cls, data: dict) -> GroundVelocity:
        """A logged velocity (:meth:`to_dict`), for a replay to fuse it again."""
        try:
            return cls(
                float(data["time_s"]),
                float(data["east_mps"]),
                float(data["north_mps"]),
                np.asarray(data["covariance_m2ps2"], dtype=float).reshape(2, 2),
                int(data["inliers"]),
                float(data["baseline_s"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise VelocityError(f"frame velocity record: {exc!r} in {data}") from exc


@dataclass(frozen=True)
class _Frame:
    features: FeatureSet
    time_s: float
    alt_agl_m: float
    heading_rad: float


class FrameVelocity:
    """Keeps the last frame's features; each new frame measures the velocity since it.

    One instance per camera stream, used from one thread.
    """

    def __init__(self, camera: Camera, config: VelocityConfig | None = None) -> None:
        self.camera, self.config = camera, config or VelocityConfig()
        conf = {"max_keypoints": self.config.max_keypoints}
        if "max_matches" in backend_class("orb").default_conf:
            conf["max_matches"] = self.config.max_keypoints  # every good match, not the best few hundred
        self._backend: FeatureBackend = create_backend("orb", **conf)
        self._last: _Frame | None = None

    def reset(self) -> None:
        """Forget the last frame: the next one only starts a new pair."""
        self._last = None

    def add(
        self,
        image: np.ndarray,
        capture_time_s: float,
        alt_agl_m: float,
        heading_deg: float,
    ) -> GroundVelocity | None:
        """The velocity from the last frame to this one; None for the first frame (or after a
        gap). Raises :class:`VelocityError` when the pair gives none; this frame is kept either way.

        ``heading_deg`` is the camera's heading at the capture (the image top), ``alt_agl_m`` its
        height above the ground.
        """
        values = (capture_time_s, alt_agl_m, heading_deg)
        if not all(math.isfinite(v) for v in values) or alt_agl_m <= 0.0:
            self._last = None
            raise VelocityError(
                "frame velocity: capture time and heading must be finite and the height above ground "
                f"positive, got {values}"
            )
        frame = _Frame(self._extract(image), capture_time_s, alt_agl_m, math.radians(heading_deg))
        last, self._last = self._last, frame
        if last is None:
            return None
        baseline = capture_time_s - last.time_s
        if not 0.0 < baseline <= self.config.max_gap_s:
            return None
        return self._velocity(last, frame, baseline)

    def _extract(self, image: np.ndarray) -> FeatureSet:
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.shape[:2] != (self.camera.height, self.camera.width):
            self._last = None
            raise VelocityError(
                f"frame velocity: expected a {self.camera.width}x{self.camera.height} uint8 frame, "
                f"got {image.shape} {image.dtype}"
            )
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
        return self._backend.extract(gray)

    def _velocity(self, last: _Frame, frame: _Frame, baseline: float) -> GroundVelocity:
        cfg, cam = self.config, self.camera
        matches = self._backend.match(last.features, frame.features)
        if len(matches) < cfg.min_inliers:
            raise VelocityError(f"frame velocity: {len(matches)} matches (need {cfg.min_inliers})")
        p = cam.undistort_points(last.features.keypoints[matches.pairs[:, 0]])
        q = cam.undistort_points(frame.features.keypoints[matches.pairs[:, 1]])
        fit, mask = cv2.estimateAffinePartial2D(p, q, method=cv2.RANSAC, ransacReprojThreshold=cfg.ransac_px)
        inliers = mask.ravel().astype(bool) if mask is not None else np.zeros(len(p), bool)
        n = int(inliers.sum())
        if fit is None or n < cfg.min_inliers or n < cfg.min_inlier_ratio * len(p):
            raise VelocityError(
                f"frame velocity: {n} inliers of {len(p)} matches "
                f"(need {cfg.min_inliers} and {cfg.min_inlier_ratio:.0%})"
            )
        scale = math.hypot(fit[0, 0], fit[1, 0])
        turn_deg = math.degrees(math.atan2(fit[1, 0], fit[0, 0]))
        if abs(scale - 1.0) > cfg.max_scale_change or abs(turn_deg) > cfg.max_turn_deg:
            raise VelocityError(
                f"frame velocity: scale {scale:.3f} and turn {turn_deg:.1f} deg between frames beyond "
                f"what the vehicle does (+-{cfg.max_scale_change:.0%}, +-{cfg.max_turn_deg:.0f} deg)"
            )
        centre = np.array([cam.cx, cam.cy])
        # Where the previous frame saw the ground now under the current frame's centre.
        seen = np.linalg.solve(fit[:, :2], centre - fit[:, 2])
        gsd = last.alt_agl_m / math.sqrt(cam.fx * cam.fy)
        right_m, forward_m = (seen - centre) * [gsd, -gsd]
        residual = q[inliers] - (p[inliers] @ fit[:, :2].T + fit[:, 2])
        rmse_px = float(np.sqrt(np.mean(np.sum(residual**2, axis=1)) / 2.0))
        shift_px = math.hypot(cfg.fit_sigmas * rmse_px / math.sqrt(n), cfg.floor_px)
        shift_m = math.hypot(shift_px * gsd, last.alt_agl_m * math.radians(cfg.tilt_jitter_deg))
        rotation = _rotation(last.heading_rad)
        along = rotation @ np.array([right_m, forward_m])
        distance = float(np.linalg.norm(along))
        unit = along / distance if distance > 0.0 else np.zeros(2)
        across = np.array([-unit[1], unit[0]])
        heading_sigma = math.radians(cfg.heading_sigma_deg)
        cov_m2 = (
            np.eye(2) * shift_m**2
            + np.outer(across, across) * (distance * heading_sigma) ** 2
            + np.outer(unit, unit) * (distance * cfg.height_sigma_frac) ** 2
        )
        velocity = along / baseline
        return GroundVelocity(
            time_s=(last.time_s + frame.time_s) / 2.0,
            east_mps=float(velocity[0]),
            north_mps=float(velocity[1]),
            covariance_m2ps2=cov_m2 / baseline**2,
            inliers=n,
            baseline_s=baseline,
        )


def _rotation(heading_rad: float) -> np.ndarray:
    """(right, forward) of a camera whose image top points at ``heading_rad`` -> (east, north)."""
    s, c = math.sin(heading_rad), math.cos(heading_rad)
    return np.array([[c, s], [-s, c]])
