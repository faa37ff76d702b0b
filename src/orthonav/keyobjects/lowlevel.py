"""Low-level key objects (points) of the multi-camera SLAM paper, with its relative descriptors
and two-stage identification.

- Gradient key points: corners of the spatially oriented brightness gradient (Shi-Tomasi).
- Extremal key points: local brightness maxima/minima kept only where they pass the local
  contrast test ``|I(x, y) - mean of the (2 dx + 1) x (2 dy + 1) window| >= T_L``.
- Relative descriptor ``D_RI = {A(n), R(n) / max R}`` over the ``N_P`` nearest key points:
  angles (measured from the direction of the nearest one, so an image rotation cancels) and
  distances normalised by the largest (so a scale change cancels).
- Two-stage identification: gradient points are matched first (their own ORB descriptors,
  ratio test, RANSAC homography); extremal points are then matched by relative descriptors
  taken against the matched gradient points, which both images share.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from orthonav.errors import OrthonavError


@dataclass(frozen=True)
class LowLevelConfig:
    max_gradient_points: int = 1000
    gradient_quality: float = 0.01
    min_distance_px: int = 5
    extremum_window_px: int = 7  # (2 dx + 1): the neighbourhood of the extremum and contrast test
    contrast_threshold: float = 12.0  # T_L in grey levels
    max_extrema: int = 2000
    neighbours: int = 6  # N_P


@dataclass
class LowLevelObjects:
    """(N, 2) gradient and (M, 2) extremal key points (x, y px) of one grey image."""

    gradient: np.ndarray
    extremal: np.ndarray

    @property
    def all(self) -> np.ndarray:
        return np.vstack([self.gradient, self.extremal])


def _check_gray(gray: np.ndarray) -> None:
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise OrthonavError(
            f"key objects: expected an (H, W) uint8 grey image, got {gray.shape} {gray.dtype}"
        )


def gradient_points(gray: np.ndarray, config: LowLevelConfig = LowLevelConfig()) -> np.ndarray:
    _check_gray(gray)
    corners = cv2.goodFeaturesToTrack(
        gray, config.max_gradient_points, config.gradient_quality, config.min_distance_px, blockSize=5
    )
    return np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)


def extremal_points(gray: np.ndarray, config: LowLevelConfig = LowLevelConfig()) -> np.ndarray:
    """Local brightness extrema that pass the local contrast test (strongest first)."""
    _check_gray(gray)
    size = config.extremum_window_px
    kernel = np.ones((size, size), np.uint8)
    smooth = cv2.GaussianBlur(gray, (3, 3), 0)
    is_max = smooth >= cv2.dilate(smooth, kernel)
    is_min = smooth <= cv2.erode(smooth, kernel)
    mean = cv2.blur(smooth.astype(np.float32), (size, size))
    contrast = np.abs(smooth.astype(np.float32) - mean)
    keep = (is_max | is_min) & (contrast >= config.contrast_threshold)
    border = size
    keep[:border], keep[-border:], keep[:, :border], keep[:, -border:] = False, False, False, False
    rows, cols = np.nonzero(keep)
    order = np.argsort(-contrast[rows, cols])[: config.max_extrema]
    return np.column_stack([cols[order], rows[order]]).astype(np.float32)


def detect_low_level(gray: np.ndarray, config: LowLevelConfig = LowLevelConfig()) -> LowLevelObjects:
    return LowLevelObjects(gradient_points(gray, config), extremal_points(gray, config))


def relative_descriptors(points: np.ndarray, anchors: np.ndarray, neighbours: int) -> np.ndarray:
    """``D_RI`` of each point over its ``neighbours`` nearest anchors: (N, 2 * neighbours).

    Columns: the angles to the 2nd..Nth nearest anchor minus the angle to the nearest one
    (radians, as cos/sin pairs would double the size: wrapped to (-pi, pi]), then R(n) / max R.
    The point itself is skipped when it is one of the anchors.
    """
    if len(anchors) < neighbours + 1:
        raise OrthonavError(f"relative descriptors need {neighbours + 1} anchor points, got {len(anchors)}")
    tree = cKDTree(anchors)
    dist, idx = tree.query(points, k=neighbours + 1)
    self_hit = dist[:, 0] < 1e-6
    dist = np.where(self_hit[:, None], dist[:, 1:], dist[:, :-1])
    idx = np.where(self_hit[:, None], idx[:, 1:], idx[:, :-1])
    vec = anchors[idx] - points[:, None, :]
    angles = np.arctan2(vec[..., 1], vec[..., 0])
    rel = np.angle(np.exp(1j * (angles - angles[:, :1])))
    radial = dist / np.maximum(dist.max(axis=1, keepdims=True), 1e-9)
    return np.hstack([rel, radial]).astype(np.float32)


def _nearest(points: np.ndarray, anchors: np.ndarray, k: int) -> np.ndarray:
    """(N, k) indices of each point's k nearest anchors, nearest first."""
    _, idx = cKDTree(anchors).query(points, k=k)
    return np.asarray(idx).reshape(len(points), k)


@dataclass
class Identification:
    """Matched pairs (index into image 1, index into image 2) per stage, and the homography."""

    gradient_pairs: np.ndarray
    extremal_pairs: np.ndarray
    homography: np.ndarray | None


def identify(
    gray1: np.ndarray, gray2: np.ndarray, config: LowLevelConfig = LowLevelConfig(), tolerance: float = 0.05
) -> tuple[LowLevelObjects, LowLevelObjects, Identification]:
    """The two-stage identification of low-level key objects between two images."""
    obj1, obj2 = detect_low_level(gray1, config), detect_low_level(gray2, config)
    orb = cv2.ORB_create()
    kp1 = [cv2.KeyPoint(float(x), float(y), 31) for x, y in obj1.gradient]
    kp2 = [cv2.KeyPoint(float(x), float(y), 31) for x, y in obj2.gradient]
    kp1, d1 = orb.compute(gray1, kp1)
    kp2, d2 = orb.compute(gray2, kp2)
    empty = Identification(np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), None)
    if d1 is None or d2 is None or len(kp1) < 8 or len(kp2) < 8:
        return obj1, obj2, empty
    obj1.gradient = np.array([k.pt for k in kp1], np.float32)
    obj2.gradient = np.array([k.pt for k in kp2], np.float32)
    knn = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(d1, d2, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < 8:
        return obj1, obj2, empty
    pairs = np.array([(m.queryIdx, m.trainIdx) for m in good], np.int64)
    h, mask = cv2.findHomography(obj1.gradient[pairs[:, 0]], obj2.gradient[pairs[:, 1]], cv2.USAC_MAGSAC, 3.0)
    if h is None:
        return obj1, obj2, empty
    gradient_pairs = pairs[mask.ravel() > 0]
    extremal_pairs = _stage_two(obj1, obj2, gradient_pairs, config.neighbours, tolerance)
    return obj1, obj2, Identification(gradient_pairs, extremal_pairs, h)


def _stage_two(
    obj1: LowLevelObjects, obj2: LowLevelObjects, anchors: np.ndarray, neighbours: int, tolerance: float
) -> np.ndarray:
    """Extremal points matched by relative descriptors against the matched gradient points.

    The matched anchors are the same physical points in both images, so a point of image 1 is
    compared with the candidates of image 2 that have the same nearest anchor, using image 1's
    anchor identities on both sides.
    """
    if len(anchors) < neighbours + 1 or not len(obj1.extremal) or not len(obj2.extremal):
        return np.zeros((0, 2), np.int64)
    a1, a2 = obj1.gradient[anchors[:, 0]], obj2.gradient[anchors[:, 1]]
    near1 = _nearest(obj1.extremal, a1, neighbours)
    desc1 = _descriptor_to(obj1.extremal, a1, near1)
    by_anchor: dict[int, list[int]] = {}
    for j, key in enumerate(_nearest(obj2.extremal, a2, 1)[:, 0]):
        by_anchor.setdefault(int(key), []).append(j)
    pairs = []
    for i, key in enumerate(near1[:, 0]):
        candidates = by_anchor.get(int(key), [])
        if not candidates:
            continue
        desc2 = _descriptor_to(obj2.extremal[candidates], a2, np.repeat(near1[i : i + 1], len(candidates), 0))
        cost = np.abs(desc2 - desc1[i]).max(axis=1)
        best = int(np.argmin(cost))
        if cost[best] < tolerance:
            pairs.append((i, candidates[best]))
    return np.array(pairs, np.int64).reshape(-1, 2)


def _descriptor_to(points: np.ndarray, anchors: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Angles (from the first anchor's direction) and normalised distances to given anchors."""
    vec = anchors[idx] - points[:, None, :]
    dist = np.linalg.norm(vec, axis=2)
    angles = np.arctan2(vec[..., 1], vec[..., 0])
    rel = np.angle(np.exp(1j * (angles - angles[:, :1])))
    radial = dist / np.maximum(dist.max(axis=1, keepdims=True), 1e-9)
    return np.hstack([rel[:, 1:] / math.pi, radial]).astype(np.float32)
