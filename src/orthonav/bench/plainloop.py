"""The simplest ORB loop, the reference ``orthonav bench speed`` times orthonav's ORB against.

ORB on the raw frame (the map's own ORB, so that descriptors compare); against each of the map
tiles orthonav's keypoints take for the prior (:func:`prior_tiles`), a brute-force Hamming
matcher with Lowe's ratio test and a RANSAC homography; the frame centre through the homography
of the tile with the most inliers. No warp, no pose, no checks: what a frame costs at the least,
and what orthonav's checks buy over it. A benchmark reference only, never a fix source.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from orthonav.camera import apply_homography
from orthonav.localize.keypoint import prior_tiles
from orthonav.localize.timing import elapsed_ms
from orthonav.mapdb import MapPackage
from orthonav.types import Prior

RATIO = 0.75  # Lowe's ratio test
RANSAC_PX = 5.0  # the homography's reprojection threshold in map pixels
MAX_TILES = 4  # LocalizerConfig.max_prior_candidates: the tiles orthonav's keypoints take


@dataclass
class PlainFix:
    """Where the loop puts the frame centre (None: no homography) and what each stage took."""

    centre: tuple[float, float] | None
    timings_ms: dict[str, float]


class PlainTileLoop:
    """The loop over one ORB map package; tiles read once and kept."""

    def __init__(self, package: MapPackage) -> None:
        self.package = package
        self._orb = package.create_backend()
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._tiles: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def locate(self, frame: np.ndarray, prior: Prior) -> PlainFix:
        """The frame centre's latitude and longitude by the tile that matches best."""
        gray = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        t0 = time.perf_counter()
        features = self._orb.extract(gray)
        timings = {"extract_ms": elapsed_ms(t0), "match_ms": 0.0, "pose_ms": 0.0}
        best, most = None, 0
        if len(features) >= 2:
            frame_px, descriptors = features.keypoints, features.descriptors
            for index in prior_tiles(self.package, prior, MAX_TILES):
                h, inliers = self._match_tile(int(index), frame_px, descriptors, timings)
                if h is not None and inliers > most:
                    best, most = h, inliers
        centre = None if best is None else self._centre(best, gray.shape)
        timings["total_ms"] = elapsed_ms(t0)
        return PlainFix(centre, timings)

    def _match_tile(
        self, index: int, frame_px: np.ndarray, descriptors: np.ndarray, timings: dict[str, float]
    ) -> tuple[np.ndarray | None, int]:
        """The homography frame px -> map px on one tile and its inlier count; times added."""
        t1 = time.perf_counter()
        tile_descriptors, map_px = self._tile(index)
        knn = self._matcher.knnMatch(descriptors, tile_descriptors, k=2)
        good = [p[0] for p in knn if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
        timings["match_ms"] += elapsed_ms(t1)
        if len(good) < 4:
            return None, 0
        t2 = time.perf_counter()
        query = frame_px[[m.queryIdx for m in good]]
        train = map_px[[m.trainIdx for m in good]].astype(np.float32)
        h, mask = cv2.findHomography(query, train, cv2.RANSAC, RANSAC_PX)
        timings["pose_ms"] += elapsed_ms(t2)
        return (h, int(mask.sum())) if h is not None else (None, 0)

    def _tile(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        if index not in self._tiles:
            features = self.package.tile_features(index)
            self._tiles[index] = (features.descriptors, self.package.tile_keypoints_map_px(index))
        return self._tiles[index]

    def _centre(self, h: np.ndarray, shape: tuple[int, ...]) -> tuple[float, float]:
        """The image centre (OpenCV pixels: the first pixel's centre at 0) on the map."""
        x, y = apply_homography(h, np.array([[(shape[1] - 1) / 2.0, (shape[0] - 1) / 2.0]]))[0]
        lat, lon = self.package.grid.pixel_to_latlon(x, y)
        return float(lat), float(lon)
