"""Guided matching: each frame keypoint against the map keypoints near where a pose puts it.

Where a pose is already known to a few map pixels (the cascade's coarse placement), a learned
matcher's attention over every pair of keypoints is mostly spent ruling out places the frame
cannot be. Here a frame keypoint is compared only with the map keypoints within ``radius_px``
of its predicted map position, by descriptor distance; a pair is kept where each is the
other's nearest among those candidates and the nearest is clearly nearer than the second
(Lowe's ratio). Cost: a k-d tree query and one distance per candidate pair, a millisecond for
a few hundred keypoints.

The radius is chosen well above the prediction's error so that the geometry stays evidence: a
random pair within ``radius_px`` agrees with the consensus to RANSAC's threshold only by the
ratio of the two areas, so a wrong placement does not lend its own pose to chance matches.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet, Matches


def guided_matches(
    query: FeatureSet,
    predicted_px: np.ndarray,
    train: FeatureSet,
    train_px: np.ndarray,
    radius_px: float,
    ratio: float = 0.9,
) -> Matches:
    """Mutual nearest descriptors among the train keypoints within ``radius_px`` of each query
    keypoint's ``predicted_px`` (both in the same pixel frame), with the ratio test."""
    if len(predicted_px) != len(query) or len(train_px) != len(train):
        raise OrthonavError("guided matching: expected one predicted position per keypoint")
    if not len(query) or not len(train):
        return Matches.empty()
    neighbours = cKDTree(train_px).query_ball_point(predicted_px, radius_px)
    counts = np.fromiter((len(n) for n in neighbours), np.int64, len(neighbours))
    if not counts.sum():
        return Matches.empty()
    qi = np.repeat(np.arange(len(query)), counts)
    ti = np.fromiter((j for n in neighbours for j in n), np.int64, int(counts.sum()))
    dist = _distances(query.descriptors[qi], train.descriptors[ti])
    best_q, second_q = _best_two(qi, dist, len(query))
    best_t, _ = _best_two(ti, dist, len(train))
    pair = best_q[qi] == np.arange(len(qi))
    mutual = pair & (best_t[ti] == np.arange(len(qi)))
    second = second_q[qi]
    clear = np.where(second >= 0, dist <= ratio * dist[np.maximum(second, 0)], True)
    keep = np.flatnonzero(mutual & clear)
    keep = keep[np.argsort(dist[keep], kind="stable")]
    return Matches(np.column_stack([qi[keep], ti[keep]]), dist[keep].astype(np.float32))


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise descriptor distances: Hamming for binary (uint8) descriptors, else L2."""
    if a.dtype == np.uint8:
        return np.unpackbits(a ^ b, axis=1).sum(1).astype(np.float64)
    diff = a.astype(np.float32) - b.astype(np.float32)
    return np.sqrt(np.einsum("nd,nd->n", diff, diff)).astype(np.float64)


def _best_two(group: np.ndarray, dist: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per group (keypoint index), the row of its smallest and second-smallest distance (-1 if
    none)."""
    order = np.lexsort((dist, group))
    sorted_groups = group[order]
    starts = np.flatnonzero(np.r_[True, sorted_groups[1:] != sorted_groups[:-1]])
    best = np.full(n, -1, np.int64)
    second = np.full(n, -1, np.int64)
    best[sorted_groups[starts]] = order[starts]
    has_second = np.r_[starts[1:], len(order)] - starts > 1
    second[sorted_groups[starts[has_second]]] = order[starts[has_second] + 1]
    return best, second
