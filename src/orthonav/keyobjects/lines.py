"""High-level geometric key objects: straight line segments (OpenCV's LSD detector, Hough as
the fallback) with a relative descriptor over the nearest segments' midpoints."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from orthonav.keyobjects.lowlevel import relative_descriptors


@dataclass(frozen=True)
class LineConfig:
    min_length_px: float = 20.0
    neighbours: int = 4
    blur_sigma: float = 1.0  # a light pre-smoothing keeps LSD off single-pixel noise


def detect_lines(gray: np.ndarray, config: LineConfig = LineConfig()) -> np.ndarray:
    """(N, 4) segments (x1, y1, x2, y2) px, at least ``min_length_px`` long, longest first."""
    image = cv2.GaussianBlur(gray, (0, 0), config.blur_sigma) if config.blur_sigma > 0 else gray
    try:
        found = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD).detect(image)[0]
    except (cv2.error, AttributeError):  # builds without LSD: the probabilistic Hough transform
        edges = cv2.Canny(image, 50, 150)
        found = cv2.HoughLinesP(edges, 1, np.pi / 180, 40, minLineLength=config.min_length_px, maxLineGap=3)
    if found is None:
        return np.zeros((0, 4), np.float32)
    segments = found.reshape(-1, 4).astype(np.float32)
    length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    keep = length >= config.min_length_px
    return segments[keep][np.argsort(-length[keep])]


def line_descriptors(segments: np.ndarray, config: LineConfig = LineConfig()) -> np.ndarray:
    """Per segment: its orientation relative to the nearest neighbour's, its length over the
    longest neighbour's, then ``D_RI`` of its midpoint over the nearest segments' midpoints."""
    mid = (segments[:, :2] + segments[:, 2:]) / 2
    rel = relative_descriptors(mid, mid, config.neighbours)
    _, idx = _nearest(mid, config.neighbours)
    theta = np.arctan2(segments[:, 3] - segments[:, 1], segments[:, 2] - segments[:, 0])
    length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    own = np.column_stack(
        [
            np.angle(np.exp(2j * (theta - theta[idx[:, 0]]))) / 2,
            length / np.maximum(length[idx].max(axis=1), 1e-9),
        ]
    )
    return np.hstack([own, rel]).astype(np.float32)


def _nearest(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(points).query(points, k=k + 1)
    return dist[:, 1:], idx[:, 1:]


def segments_agree(
    reference: np.ndarray, other: np.ndarray, endpoint_px: float = 3.0, angle_deg: float = 5.0
) -> np.ndarray:
    """(N, M) bool: segment i of ``reference`` and j of ``other`` are the same segment, i.e. both
    endpoints lie within ``endpoint_px`` (in either order) and the directions within ``angle_deg``."""
    return _agree(reference.reshape(-1, 1, 2, 2), other.reshape(1, -1, 2, 2), endpoint_px, angle_deg)


def _agree(a: np.ndarray, b: np.ndarray, endpoint_px: float, angle_deg: float) -> np.ndarray:
    """:func:`segments_agree` on broadcastable (..., 2, 2) endpoint arrays."""
    same = np.linalg.norm(a - b, axis=-1).max(axis=-1)
    swapped = np.linalg.norm(a - b[..., ::-1, :], axis=-1).max(axis=-1)
    theta_a = np.arctan2(a[..., 1, 1] - a[..., 0, 1], a[..., 1, 0] - a[..., 0, 0])
    theta_b = np.arctan2(b[..., 1, 1] - b[..., 0, 1], b[..., 1, 0] - b[..., 0, 0])
    turn = np.abs(np.angle(np.exp(2j * (theta_a - theta_b)))) / 2  # undirected lines: modulo pi
    return (np.minimum(same, swapped) <= endpoint_px) & (turn <= np.radians(angle_deg))


def transform_segments(segments: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Both endpoints of every segment through a 2x3 affine or 3x3 homography matrix."""
    ends = segments.reshape(-1, 2).astype(np.float64)
    if matrix.shape == (2, 3):
        moved = ends @ matrix[:, :2].T + matrix[:, 2]
    else:
        homog = np.column_stack([ends, np.ones(len(ends))]) @ matrix.T
        moved = homog[:, :2] / homog[:, 2:]
    return moved.reshape(-1, 4).astype(np.float32)


@dataclass(frozen=True)
class LineMatchConfig:
    ratio: float = 0.8  # nearest / second nearest descriptor distance
    endpoint_px: float = 3.0  # geometric check, after the transform
    angle_deg: float = 5.0
    ransac_px: float = 3.0  # midpoint reprojection threshold of the similarity fit


def match_lines(
    segments1: np.ndarray,
    descriptors1: np.ndarray,
    segments2: np.ndarray,
    descriptors2: np.ndarray,
    config: LineMatchConfig = LineMatchConfig(),
    transform: np.ndarray | None = None,
) -> np.ndarray:
    """(K, 2) index pairs of segments matched by their descriptors, then checked geometrically.

    Descriptors: nearest neighbour (Euclidean) with the ratio test. Geometry: with a known
    ``transform`` (2x3 or 3x3, image 1 -> image 2) the pair must agree after it (endpoints and
    angle, :func:`segments_agree`); without one, a similarity is fitted to the candidate pairs'
    midpoints by RANSAC and the same check applies after it.
    """
    if len(segments1) == 0 or len(segments2) < 2:
        return np.zeros((0, 2), np.int64)
    dist = np.linalg.norm(descriptors1[:, None, :] - descriptors2[None, :, :], axis=2)
    order = np.argsort(dist, axis=1)[:, :2]
    rows = np.arange(len(segments1))
    best, second = dist[rows, order[:, 0]], dist[rows, order[:, 1]]
    keep = best < config.ratio * np.maximum(second, 1e-9)
    pairs = np.column_stack([rows[keep], order[keep, 0]]).astype(np.int64)
    if transform is None:
        transform = _fit_similarity(segments1[pairs[:, 0]], segments2[pairs[:, 1]], config.ransac_px)
        if transform is None:
            return np.zeros((0, 2), np.int64)
    moved = transform_segments(segments1[pairs[:, 0]], transform)
    ends1, ends2 = moved.reshape(-1, 2, 2), segments2[pairs[:, 1]].reshape(-1, 2, 2)
    return pairs[_agree(ends1, ends2, config.endpoint_px, config.angle_deg)]


def _fit_similarity(segments1: np.ndarray, segments2: np.ndarray, ransac_px: float) -> np.ndarray | None:
    if len(segments1) < 3:
        return None
    mid1 = (segments1[:, :2] + segments1[:, 2:]) / 2
    mid2 = (segments2[:, :2] + segments2[:, 2:]) / 2
    matrix, _ = cv2.estimateAffinePartial2D(mid1, mid2, method=cv2.RANSAC, ransacReprojThreshold=ransac_px)
    return matrix
