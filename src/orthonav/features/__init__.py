"""Feature backends behind one interface: extract keypoints/descriptors, match two sets."""

from orthonav.features import opencv as _opencv  # noqa: F401  (registers orb, sift)
from orthonav.features.base import (
    FeatureBackend,
    FeatureSet,
    Matches,
    available_backends,
    create_backend,
    register,
)

__all__ = [
    "FeatureBackend",
    "FeatureSet",
    "Matches",
    "available_backends",
    "create_backend",
    "register",
]
