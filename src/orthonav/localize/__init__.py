"""Localization: candidate tiles, keypoint matching, pose from homography, quality -> Fix."""

from orthonav.localize.candidates import all_tiles, motion_prediction, start_block, tiles_near
from orthonav.localize.localizer import Localizer, LocalizerConfig, check_backend, load_frame
from orthonav.localize.types import Fix, FixSource, Pose, Prior, footprint_latlon

__all__ = [
    "Fix",
    "FixSource",
    "Localizer",
    "LocalizerConfig",
    "Pose",
    "Prior",
    "all_tiles",
    "check_backend",
    "footprint_latlon",
    "load_frame",
    "motion_prediction",
    "start_block",
    "tiles_near",
]
