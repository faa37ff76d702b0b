"""Semantic high-level key objects from a colour segmentation that needs no trained model:
water, vegetation, bare soil and roads/buildings, each connected region one key object.

Rules on colour (8-bit BGR): vegetation by the excess-green index ``2G - R - B``; water dark
or blue-dominant with low green excess; roads/buildings grey (low saturation) and not dark;
bare soil the rest with red over blue (browns, sand). A rule-based segmentation is coarse;
it is what colour-aware high-level objects need without downloading a network.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from orthonav.errors import OrthonavError

CLASSES = ("unknown", "water", "vegetation", "bare_soil", "built")


@dataclass(frozen=True)
class RegionConfig:
    exg_vegetation: float = 20.0
    water_max_value: float = 60.0
    grey_max_saturation: float = 40.0
    min_area_px: int = 200
    smooth_px: int = 5


@dataclass(frozen=True)
class Region:
    """One connected region of a class: centroid (x, y) px, area px, class name."""

    x: float
    y: float
    area_px: int
    label: str


def classify(bgr: np.ndarray, config: RegionConfig = RegionConfig()) -> np.ndarray:
    """(H, W) uint8 class index into :data:`CLASSES`."""
    if bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint8:
        raise OrthonavError(f"regions: expected an (H, W, 3) uint8 BGR image, got {bgr.shape} {bgr.dtype}")
    b, g, r = (c.astype(np.float32) for c in cv2.split(cv2.GaussianBlur(bgr, (5, 5), 0)))
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    sat, val = hsv[..., 1].astype(np.float32), hsv[..., 2].astype(np.float32)
    exg = 2 * g - r - b
    labels = np.full(bgr.shape[:2], CLASSES.index("bare_soil"), np.uint8)
    labels[(sat < config.grey_max_saturation) & (val >= config.water_max_value)] = CLASSES.index("built")
    labels[exg > config.exg_vegetation] = CLASSES.index("vegetation")
    water = ((val < config.water_max_value) | ((b > r + 10) & (b >= g))) & (exg <= config.exg_vegetation)
    labels[water] = CLASSES.index("water")
    if config.smooth_px > 1:
        labels = cv2.medianBlur(labels, config.smooth_px | 1)
    return labels


def regions(labels: np.ndarray, config: RegionConfig = RegionConfig()) -> list[Region]:
    """Connected regions of each class at least ``min_area_px`` large, largest first."""
    return region_map(labels, config)[0]


def region_map(labels: np.ndarray, config: RegionConfig = RegionConfig()) -> tuple[list[Region], np.ndarray]:
    """:func:`regions` and an (H, W) int32 image of each pixel's index in that list (-1: none),
    which links points and lines to the region they lie in."""
    found, masks = [], []
    for index, name in enumerate(CLASSES[1:], start=1):
        count, components, stats, centroids = cv2.connectedComponentsWithStats(
            (labels == index).astype(np.uint8)
        )
        for k in range(1, count):
            area = int(stats[k, cv2.CC_STAT_AREA])
            if area >= config.min_area_px:
                found.append(Region(float(centroids[k, 0]), float(centroids[k, 1]), area, name))
                masks.append((components, k))
    order = sorted(range(len(found)), key=lambda i: -found[i].area_px)
    ids = np.full(labels.shape, -1, np.int32)
    for rank, i in enumerate(order):
        components, k = masks[i]
        ids[components == k] = rank
    return [found[i] for i in order], ids


def class_fractions(labels: np.ndarray) -> dict[str, float]:
    total = labels.size
    return {name: float(np.count_nonzero(labels == i)) / total for i, name in enumerate(CLASSES)}
