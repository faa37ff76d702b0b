"""Camera model: intrinsics, attitude, ground footprint and ground<->image homographies."""

from orthonav.camera.model import Camera
from orthonav.camera.pose import (
    BODY_FROM_CAMERA,
    ENU_FROM_NED,
    AttitudePrior,
    CameraPose,
    apply_homography,
    footprint_enu,
    ground_to_image_homography,
    image_corners,
    ned_from_body,
    pixel_to_ground,
    planar_pose_candidates,
    pose_from_homography,
    project_ground,
    project_points,
    refine_pose,
    rotation_enu_from_camera,
)

__all__ = [
    "BODY_FROM_CAMERA",
    "ENU_FROM_NED",
    "AttitudePrior",
    "Camera",
    "CameraPose",
    "apply_homography",
    "footprint_enu",
    "ground_to_image_homography",
    "image_corners",
    "ned_from_body",
    "pixel_to_ground",
    "planar_pose_candidates",
    "pose_from_homography",
    "project_ground",
    "project_points",
    "refine_pose",
    "rotation_enu_from_camera",
]
