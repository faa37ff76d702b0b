"""Key objects of the multi-camera SLAM paper: low-level points (gradient + contrast-tested
extrema) with relative descriptors and two-stage identification, line segments, colour
region classes, line matching, and the map model with its base-viewpoint choice."""

from orthonav.keyobjects.lines import (
    LineConfig,
    LineMatchConfig,
    detect_lines,
    line_descriptors,
    match_lines,
    segments_agree,
    transform_segments,
)
from orthonav.keyobjects.lowlevel import (
    Identification,
    LowLevelConfig,
    LowLevelObjects,
    detect_low_level,
    extremal_points,
    gradient_points,
    identify,
    relative_descriptors,
)
from orthonav.keyobjects.model import (
    HIGH_LEVEL,
    LOW_LEVEL,
    KeyObjectCloud,
    KeyObjectMap,
    place,
    relative_pose,
)
from orthonav.keyobjects.regions import (
    CLASSES,
    Region,
    RegionConfig,
    class_fractions,
    classify,
    region_map,
    regions,
)

__all__ = [
    "CLASSES",
    "HIGH_LEVEL",
    "LOW_LEVEL",
    "Identification",
    "KeyObjectCloud",
    "KeyObjectMap",
    "LineConfig",
    "LineMatchConfig",
    "LowLevelConfig",
    "LowLevelObjects",
    "Region",
    "RegionConfig",
    "class_fractions",
    "classify",
    "detect_lines",
    "detect_low_level",
    "extremal_points",
    "gradient_points",
    "identify",
    "line_descriptors",
    "match_lines",
    "place",
    "region_map",
    "regions",
    "relative_descriptors",
    "relative_pose",
    "segments_agree",
    "transform_segments",
]
