"""What XFeat's two runtimes share (torch in :mod:`.xfeat`, ONNX Runtime in :mod:`.onnx_xfeat`): the
configuration (a map package built by one is read by the other), padding to the network's stride,
and the crop back to the image (both match by :func:`~orthonav.features.base.mutual_nearest`). Numpy
only, so that the ONNX path runs without torch.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureSet

XFEAT_CONF: dict[str, Any] = {"max_keypoints": 1024, "detection_threshold": 0.05, "max_matches": 300}
XFEAT_MNN_CONF: dict[str, Any] = {**XFEAT_CONF, "min_cossim": 0.82}
XFEAT_GLUE_CONF: dict[str, Any] = {**XFEAT_CONF, "match_threshold": 0.1}  # xfeat: LighterGlue
DESCRIPTOR_SIZE = 64
STRIDE = 32  # XFeat resizes to a multiple of 32; padding instead keeps keypoints exact


def pad_to_stride(gray: np.ndarray) -> np.ndarray:
    """The image zero-padded on the right and bottom to multiples of :data:`STRIDE`."""
    h, w = gray.shape
    padded = np.zeros((-(-h // STRIDE) * STRIDE, -(-w // STRIDE) * STRIDE), np.uint8)
    padded[:h, :w] = gray
    return padded


def keep_inside(features: FeatureSet, mask: np.ndarray | None) -> FeatureSet:
    """The features on the image (not its padding; ``features.image_size`` is the image's) and on
    ``mask``'s nonzero pixels."""
    if features.image_size is None:
        raise OrthonavError("XFeat features without their image size cannot be cropped to the image")
    w, h = features.image_size
    inside = (features.keypoints[:, 0] <= w - 1) & (features.keypoints[:, 1] <= h - 1)
    return features.subset(np.flatnonzero(inside)).inside(mask)
