"""The SLAM factor graph in gtsam, optimised incrementally with iSAM2.

Variables: one ``Pose3`` per vehicle and keyframe (ENU position, rotation body FRD -> ENU) and
one ``Point3`` per landmark (ENU metres). Factors:

- visual odometry: a ``BetweenFactorPose3`` from each :class:`~orthonav.odometry.Motion`
  (forward/right/yaw with their covariance; roll/pitch and height increments loosely);
- attitude: the AHRS gravity direction (``AttitudeFactorPose3``, roll and pitch only);
- altitude: the barometer, a ``GPSFactor`` loose in east/north;
- map fixes: a ``GPSFactor`` with the fix's 2x2 ENU covariance and the altitude's sigma;
- landmarks: a ``GenericProjectionFactorCal3_S2`` per observation, through the rig camera's
  extrinsics (``body_P_sensor``), with a Huber kernel; a loose prior holds each landmark near
  the ground plane (a DEM's role; the simulation's ground is flat);
- inter-UAV: landmarks observed by several vehicles tie their poses together, and a
  ``BearingRangeFactorPose3`` carries the baseline measured from the other UAV's image.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.slam.rig import Rig, enu_r_body
from orthonav.types import positive_definite, worst_sigma

try:
    import gtsam
except ImportError:  # the ``slam`` extra is absent: the module still imports, the graph refuses
    gtsam = None

# The sigma of a direction a factor does not measure (the barometer's and the ground prior's
# east/north). Such factors are centred on the variable's initial value: even this weak a pull
# towards a fixed point would otherwise turn the whole map about its weakly held heading.
_BIG_SIGMA = 1.0e6
_DOWN_ENU = np.array([0.0, 0.0, -1.0])


def require_gtsam() -> None:
    if gtsam is None:
        raise OrthonavError("SLAM needs gtsam: install the 'slam' extra (pip install 'orthonav[slam]')")


@dataclass(frozen=True)
class GraphConfig:
    """Noise of the measurements the graph does not get a covariance with, and iSAM2 settings."""

    pixel_sigma_px: float = 1.5
    huber_k: float = 1.345
    attitude_sigma_deg: float = 0.3
    # Floors added to the odometry's own covariance, which counts only its inliers' noise: in
    # the simulation its errors (planar decomposition, resampling) are 2-3 times larger.
    odometry_floor_m: float = 1.0
    odometry_yaw_floor_deg: float = 0.05
    odometry_roll_pitch_sigma_deg: float = 0.5
    odometry_height_sigma_m: float = 2.0
    baro_sigma_m: float = 2.0
    ground_sigma_m: float = 10.0
    start_sigma_m: float = 5.0
    start_yaw_sigma_deg: float = 1.0
    relinearize_threshold: float = 0.01
    extra_iterations: int = 1

    def to_dict(self) -> dict:
        return asdict(self)


def pose_key(uav: int, keyframe: int) -> int:
    return gtsam.symbol(chr(ord("a") + uav), keyframe)


def landmark_key(landmark: int) -> int:
    return gtsam.symbol("l", landmark)


def body_pose(
    east_m: float, north_m: float, alt_m: float, yaw_deg: float, pitch_deg: float = 0.0, roll_deg: float = 0.0
) -> gtsam.Pose3:
    """A vehicle pose: body FRD -> ENU rotation and the body origin in ENU."""
    return gtsam.Pose3(
        gtsam.Rot3(enu_r_body(yaw_deg, pitch_deg, roll_deg)), np.array([east_m, north_m, alt_m])
    )


def yaw_deg_of(pose: gtsam.Pose3) -> float:
    """Heading (clockwise from north) of a body pose: the direction of its forward axis."""
    forward = pose.rotation().matrix()[:, 0]
    return math.degrees(math.atan2(forward[0], forward[1])) % 360.0


def odometry_step(motion: object, climb_m: float = 0.0) -> gtsam.Pose3:
    """A VO motion as a body-frame pose increment: forward, right, down; a clockwise yaw is +z (down)."""
    return gtsam.Pose3(
        gtsam.Rot3.Rz(math.radians(motion.dyaw_deg)), np.array([motion.forward_m, motion.right_m, -climb_m])
    )


def check_motion(motion: object, where: str) -> np.ndarray:
    """The motion's 3x3 covariance, or an error when the measurement cannot be used."""
    values = [getattr(motion, n, None) for n in ("right_m", "forward_m", "dyaw_deg")]
    cov = np.asarray(getattr(motion, "covariance", None), dtype=float)
    if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
        raise OrthonavError(
            f"{where}: odometry right_m, forward_m, dyaw_deg must be finite numbers, got {values}"
        )
    if cov.shape != (3, 3) or not np.all(np.isfinite(cov)) or not np.allclose(cov, cov.T, atol=1e-9):
        raise OrthonavError(f"{where}: odometry covariance must be a finite symmetric 3x3 matrix")
    if not positive_definite(cov):
        raise OrthonavError(f"{where}: odometry covariance must be positive definite")
    return cov


class SlamGraph:
    """Poses, landmarks and factors of one or several vehicles, solved by iSAM2 per keyframe."""

    def __init__(self, rigs: list[Rig], config: GraphConfig | None = None) -> None:
        require_gtsam()
        self.rigs = rigs
        self.config = config or GraphConfig()
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        params.relinearizeSkip = 1
        self.isam = gtsam.ISAM2(params)
        self._factors = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self.estimate = gtsam.Values()
        self._calibrations = [
            [gtsam.Cal3_S2(c.camera.fx, c.camera.fy, 0.0, c.camera.cx, c.camera.cy) for c in rig.cameras]
            for rig in rigs
        ]
        self._extrinsics = [
            [gtsam.Pose3(gtsam.Rot3(c.body_r_camera), np.asarray(c.lever_arm_m, float)) for c in rig.cameras]
            for rig in rigs
        ]
        c = self.config
        self._pixel_noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(c.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, c.pixel_sigma_px),
        )
        self._ground_noise = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([_BIG_SIGMA, _BIG_SIGMA, c.ground_sigma_m])
        )
        self._attitude_noise = gtsam.noiseModel.Isotropic.Sigma(2, math.radians(c.attitude_sigma_deg))
        self.landmarks: set[int] = set()
        self.counts = {"odometry": 0, "fixes": 0, "baselines": 0, "observations": 0}

    # -- variables ------------------------------------------------------------------------

    def add_pose(self, uav: int, keyframe: int, initial: gtsam.Pose3) -> None:
        self._values.insert(pose_key(uav, keyframe), initial)

    def add_start_prior(self, uav: int, keyframe: int, pose: gtsam.Pose3) -> None:
        """Where the vehicle starts (launch point and compass), fixing the gauge."""
        c = self.config
        rot = math.radians(c.attitude_sigma_deg)
        sigmas = np.array(
            [rot, rot, math.radians(c.start_yaw_sigma_deg), c.start_sigma_m, c.start_sigma_m, c.baro_sigma_m]
        )
        self._factors.add(
            gtsam.PriorFactorPose3(pose_key(uav, keyframe), pose, gtsam.noiseModel.Diagonal.Sigmas(sigmas))
        )

    def add_landmark(self, landmark: int, initial_enu: np.ndarray) -> None:
        key = landmark_key(landmark)
        self._values.insert(key, np.asarray(initial_enu, float))
        ground = np.array([initial_enu[0], initial_enu[1], 0.0])
        self._factors.add(gtsam.PriorFactorPoint3(key, ground, self._ground_noise))
        self.landmarks.add(landmark)

    # -- factors --------------------------------------------------------------------------

    def add_odometry(self, uav: int, k_from: int, k_to: int, motion: object, dheight_m: float = 0.0) -> None:
        """A visual-odometry step along the previous frame's axes (level nadir camera: the body's)."""
        c = self.config
        floors = np.array([c.odometry_floor_m, c.odometry_floor_m, c.odometry_yaw_floor_deg]) ** 2
        cov3 = check_motion(motion, f"uav {uav} keyframe {k_to}") + np.diag(floors)
        rp = math.radians(c.odometry_roll_pitch_sigma_deg) ** 2
        yaw_scale = math.radians(1.0)
        cov = np.zeros((6, 6))
        cov[0, 0] = cov[1, 1] = rp
        cov[5, 5] = c.odometry_height_sigma_m**2
        # Pose3 tangent order: (rx, ry, rz, tx, ty, tz) = (roll, pitch, yaw, forward, right, down).
        index = {0: 4, 1: 3, 2: 2}  # motion (right, forward, dyaw) -> tangent index
        scale = {0: 1.0, 1: 1.0, 2: yaw_scale}
        for i in range(3):
            for j in range(3):
                cov[index[i], index[j]] = cov3[i, j] * scale[i] * scale[j]
        self._factors.add(
            gtsam.BetweenFactorPose3(
                pose_key(uav, k_from),
                pose_key(uav, k_to),
                odometry_step(motion, dheight_m),
                gtsam.noiseModel.Gaussian.Covariance(cov),
            )
        )
        self.counts["odometry"] += 1

    def add_attitude(self, uav: int, keyframe: int, pitch_deg: float, roll_deg: float) -> None:
        """AHRS roll/pitch: the body-frame direction of gravity."""
        down_body = enu_r_body(0.0, pitch_deg, roll_deg).T @ _DOWN_ENU
        self._factors.add(
            gtsam.AttitudeFactorPose3(
                pose_key(uav, keyframe), gtsam.Unit3(_DOWN_ENU), self._attitude_noise, gtsam.Unit3(down_body)
            )
        )

    def add_altitude(self, uav: int, keyframe: int, alt_m: float) -> None:
        """The barometer's height above the (flat) ground."""
        sigmas = np.array([_BIG_SIGMA, _BIG_SIGMA, self.config.baro_sigma_m])
        self._factors.add(
            gtsam.GPSFactor(
                pose_key(uav, keyframe),
                np.array([*self.pose(uav, keyframe).translation()[:2], alt_m]),
                gtsam.noiseModel.Diagonal.Sigmas(sigmas),
            )
        )

    def add_fix(
        self, uav: int, keyframe: int, east_m: float, north_m: float, cov_enu_m2: np.ndarray, alt_m: float
    ) -> None:
        """An absolute map fix (position under the vehicle) with its horizontal covariance."""
        cov = np.zeros((3, 3))
        cov[:2, :2] = np.asarray(cov_enu_m2, float)
        cov[2, 2] = _BIG_SIGMA**2  # the barometer owns the height
        self._factors.add(
            gtsam.GPSFactor(
                pose_key(uav, keyframe),
                np.array([east_m, north_m, alt_m]),
                gtsam.noiseModel.Gaussian.Covariance(cov),
            )
        )
        self.counts["fixes"] += 1

    def add_baseline(
        self,
        uav_from: int,
        uav_to: int,
        keyframe: int,
        bearing_body: np.ndarray,
        range_m: float,
        bearing_sigma_rad: float,
        range_sigma_m: float,
    ) -> None:
        """Inter-UAV: where the other vehicle is, seen from this one (unit bearing in FRD, range)."""
        noise = gtsam.noiseModel.Diagonal.Sigmas(
            np.array([bearing_sigma_rad, bearing_sigma_rad, range_sigma_m])
        )
        self._factors.add(
            gtsam.BearingRangeFactorPose3(
                pose_key(uav_from, keyframe),
                pose_key(uav_to, keyframe),
                gtsam.Unit3(np.asarray(bearing_body, float)),
                float(range_m),
                noise,
            )
        )
        self.counts["baselines"] += 1

    def add_observation(self, uav: int, keyframe: int, camera: int, landmark: int, pixel: np.ndarray) -> None:
        self._factors.add(
            gtsam.GenericProjectionFactorCal3_S2(
                np.asarray(pixel, float),
                self._pixel_noise,
                pose_key(uav, keyframe),
                landmark_key(landmark),
                self._calibrations[uav][camera],
                False,
                False,
                self._extrinsics[uav][camera],
            )
        )
        self.counts["observations"] += 1

    # -- solving and reading --------------------------------------------------------------

    def update(self) -> None:
        """One iSAM2 step with everything added since the last one."""
        try:
            self.isam.update(self._factors, self._values)
            for _ in range(self.config.extra_iterations):  # relinearise what the new factors moved
                self.isam.update()
        except RuntimeError as exc:  # gtsam's IndeterminantLinearSystemException and kin
            raise OrthonavError(f"SLAM graph: the system is not solvable ({exc})") from None
        self._factors = gtsam.NonlinearFactorGraph()
        self._values = gtsam.Values()
        self.estimate = self.isam.calculateEstimate()

    def has_pose(self, uav: int, keyframe: int) -> bool:
        key = pose_key(uav, keyframe)
        return self.estimate.exists(key) or self._values.exists(key)

    def pose(self, uav: int, keyframe: int) -> gtsam.Pose3:
        """The latest estimate of a pose (its initial value before its first update)."""
        key = pose_key(uav, keyframe)
        return self.estimate.atPose3(key) if self.estimate.exists(key) else self._values.atPose3(key)

    def position_sigma_m(self, uav: int, keyframe: int) -> float:
        """1-sigma of the worst horizontal direction (iSAM2's marginal, rotated to ENU)."""
        pose = self.pose(uav, keyframe)
        cov = self.isam.marginalCovariance(pose_key(uav, keyframe))[3:, 3:]
        r = pose.rotation().matrix()
        return worst_sigma((r @ cov @ r.T)[:2, :2])

    def landmark(self, landmark: int) -> np.ndarray:
        return np.asarray(self.estimate.atPoint3(landmark_key(landmark)), float)
