"""Visual odometry for a downward camera: frame-to-frame motion in metres, keyframes, a local
map of triangulated landmarks, and runs over geotagged photo sequences."""

from orthonav.odometry.motion import METHODS, Motion, MotionConfig, OdometryError, estimate_motion

__all__ = ["METHODS", "Motion", "MotionConfig", "OdometryError", "estimate_motion"]
