"""Classical OpenCV backends: ORB (binary, Hamming) and SIFT (float, L2), with ratio tests."""

from __future__ import annotations

from typing import Any, ClassVar

import cv2
import numpy as np

from orthonav.features.base import FeatureBackend, FeatureSet, Matches, Runtime, register


def _ratio_test(knn: list, ratio: float, max_matches: int) -> Matches:
    """Lowe's ratio test on k=2 matches; keep the ``max_matches`` best by distance."""
    good = [pair[0] for pair in knn if len(pair) == 2 and pair[0].distance < ratio * pair[1].distance]
    if not good:
        return Matches.empty()
    good.sort(key=lambda m: m.distance)
    good = good[:max_matches]
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in good], np.int64)
    return Matches(pairs, np.array([m.distance for m in good], np.float32))


def _to_featureset(keypoints: list, descriptors: np.ndarray | None, empty: FeatureSet) -> FeatureSet:
    if descriptors is None or not keypoints:
        return empty
    pts = np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2)
    scores = np.array([k.response for k in keypoints], np.float32)
    return FeatureSet(pts, descriptors, scores)


class _KnnBackend(FeatureBackend):
    """Shared knn + ratio-test matching for OpenCV descriptors."""

    norm: int
    rotation_invariant = True  # both compute a dominant orientation per keypoint

    def __init__(self, runtime: Runtime | None = None, **conf) -> None:
        super().__init__(runtime, **conf)
        self._matcher = cv2.BFMatcher(self.norm)
        # Local contrast equalisation evens out sun, season and sensor differences.
        self._clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)) if self.conf["clahe"] else None

    def _prepare(self, gray: np.ndarray) -> np.ndarray:
        return self._clahe.apply(gray) if self._clahe is not None else gray

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        if len(query) < 2 or len(train) < 2:
            return Matches.empty()
        knn = self._matcher.knnMatch(query.descriptors, train.descriptors, k=2)
        return _ratio_test(knn, self.conf["ratio"], self.conf["max_matches"])


@register("orb")
class OrbBackend(_KnnBackend):
    """ORB: oriented FAST + rotated BRIEF, 256-bit descriptors, Hamming distance."""

    norm = cv2.NORM_HAMMING
    default_conf: ClassVar[dict[str, Any]] = {
        "max_keypoints": 1024,
        "scale_factor": 1.2,
        "n_levels": 8,
        "fast_threshold": 10,
        "clahe": True,
        "ratio": 0.8,
        "max_matches": 300,
    }

    def __init__(self, runtime: Runtime | None = None, **conf) -> None:
        super().__init__(runtime, **conf)
        c = self.conf
        self._orb = cv2.ORB_create(
            nfeatures=int(c["max_keypoints"]),
            scaleFactor=float(c["scale_factor"]),
            nlevels=int(c["n_levels"]),
            fastThreshold=int(c["fast_threshold"]),
            edgeThreshold=19,
            patchSize=19,
        )

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        kps, desc = self._orb.detectAndCompute(self._prepare(gray), mask)
        features = _to_featureset(kps, desc, self.empty())
        if len(features):
            # OpenCV maps a pyramid level's keypoint to the image as pt * s (s = scale_factor^octave);
            # with pixel centres at integers the map is (pt + 0.5) s - 0.5, so every coarse-level
            # keypoint sits 0.5 (s - 1) px up-left of its feature. Undo that shift.
            s = np.power(np.float32(self.conf["scale_factor"]), np.array([k.octave for k in kps], np.float32))
            features.keypoints += (0.5 * (s - 1.0))[:, None]
        return features

    @property
    def descriptor_size(self) -> int:
        return 32

    @property
    def descriptor_dtype(self) -> np.dtype:
        return np.dtype(np.uint8)


@register("sift")
class SiftBackend(_KnnBackend):
    """SIFT: difference-of-Gaussians keypoints, 128-d float descriptors, L2 distance."""

    norm = cv2.NORM_L2
    default_conf: ClassVar[dict[str, Any]] = {
        "max_keypoints": 1024,
        "contrast_threshold": 0.02,
        "clahe": True,
        "ratio": 0.8,
        "max_matches": 300,
    }

    def __init__(self, runtime: Runtime | None = None, **conf) -> None:
        super().__init__(runtime, **conf)
        self._sift = cv2.SIFT_create(
            nfeatures=int(self.conf["max_keypoints"]),
            contrastThreshold=float(self.conf["contrast_threshold"]),
        )

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        kps, desc = self._sift.detectAndCompute(self._prepare(gray), mask)
        return _to_featureset(kps, desc, self.empty())

    @property
    def descriptor_size(self) -> int:
        return 128

    @property
    def descriptor_dtype(self) -> np.dtype:
        return np.dtype(np.float32)
