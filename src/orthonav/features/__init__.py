"""Feature backends behind one interface: extract keypoints/descriptors, match a frame's set
against one or many map tiles. Classical backends (orb, sift) need only OpenCV; learned ones
(xfeat, xfeat-mnn, aliked, aliked-n16rot, disk, superpoint) need the ``learned`` extra and are
imported on first use. Those in :func:`onnx_backends` also run under ONNX Runtime without torch
(``Runtime(engine="onnx")``, or $ORTHONAV_RUNTIME=onnx, or where torch is not installed)."""

from orthonav.features import opencv as _opencv  # noqa: F401  (registers orb, sift)
from orthonav.features.base import (
    ENGINES,
    FeatureBackend,
    FeatureSet,
    Matches,
    Runtime,
    available_backends,
    backend_class,
    backend_engine,
    create_backend,
    known_backends,
    mutual_nearest,
    onnx_backends,
    register,
    weight_keys,
)

__all__ = [
    "ENGINES",
    "FeatureBackend",
    "FeatureSet",
    "Matches",
    "Runtime",
    "available_backends",
    "backend_class",
    "backend_engine",
    "create_backend",
    "known_backends",
    "mutual_nearest",
    "onnx_backends",
    "register",
    "weight_keys",
]
