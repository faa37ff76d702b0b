"""Multi-camera and multi-UAV SLAM: a rig with known extrinsics, landmarks across cameras and
vehicles, a gtsam pose graph solved by iSAM2 (odometry, attitude, altitude, map fixes,
landmarks, inter-UAV baselines), two-UAV stereo with a measured baseline, and ATE/RPE metrics.

The rig, the metrics and the stereo geometry need only numpy/OpenCV; the graph and the
simulation need gtsam (the ``slam`` extra) and import it on use.
"""

from orthonav.slam.metrics import ate_m, landmark_errors_m, rpe_m
from orthonav.slam.rig import Rig, RigCamera, enu_r_body, validate_rig
from orthonav.slam.stereo import (
    Baseline,
    Sighting,
    StereoPair,
    baseline_from_sighting,
    best_pair,
    triangulate,
)

__all__ = [
    "Baseline",
    "Rig",
    "RigCamera",
    "Sighting",
    "StereoPair",
    "ate_m",
    "baseline_from_sighting",
    "best_pair",
    "enu_r_body",
    "landmark_errors_m",
    "rpe_m",
    "triangulate",
    "validate_rig",
]
