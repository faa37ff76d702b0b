"""Guided matching: a frame keypoint meets only the map keypoints near its predicted place, and
keeps a pair only where both are each other's nearest descriptor there and the nearest is clear."""

from __future__ import annotations

import numpy as np
import pytest

from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet
from orthonav.localize.guided import guided_matches

SIZE = 500


def _unit(rng: np.random.Generator, n: int, dim: int = 128) -> np.ndarray:
    d = rng.normal(size=(n, dim)).astype(np.float32)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _features(points: np.ndarray, descriptors: np.ndarray) -> FeatureSet:
    return FeatureSet(points.astype(np.float32), descriptors, np.ones(len(points), np.float32), (SIZE, SIZE))


@pytest.fixture
def scene() -> tuple[FeatureSet, np.ndarray, FeatureSet, np.ndarray]:
    """300 map keypoints; a frame of 100 of them (noisy descriptors) predicted within 5 px."""
    rng = np.random.default_rng(3)
    map_px = rng.uniform(0, SIZE, (300, 2))
    map_desc = _unit(rng, 300)
    twins = rng.choice(300, 100, replace=False)
    noisy = map_desc[twins] + 0.03 * rng.normal(size=(100, 128)).astype(np.float32)
    predicted = map_px[twins] + rng.uniform(-5, 5, (100, 2))
    query = _features(rng.uniform(0, 200, (100, 2)), noisy)
    return query, predicted, _features(map_px, map_desc), twins


def test_each_keypoint_finds_its_twin_near_its_predicted_place(scene) -> None:
    query, predicted, train, twins = scene
    m = guided_matches(query, predicted, train, train.keypoints, radius_px=20.0)
    assert len(m) >= 95
    np.testing.assert_array_equal(m.pairs[:, 1], twins[m.pairs[:, 0]])
    assert np.all(np.diff(m.distances) >= 0)  # best first, as Matches expects


def test_a_twin_beyond_the_radius_is_never_matched(scene) -> None:
    query, predicted, train, twins = scene
    m = guided_matches(query, predicted + 30.0, train, train.keypoints, radius_px=20.0)
    assert not np.any(m.pairs[:, 1] == twins[m.pairs[:, 0]])
    reach = np.hypot(*(train.keypoints[m.pairs[:, 1]] - (predicted + 30.0)[m.pairs[:, 0]]).T)
    assert np.all(reach <= 20.0)


def test_an_ambiguous_candidate_fails_the_ratio_test() -> None:
    """Two map keypoints as alike as the frame's is to either: no pair, unless the ratio is 1."""
    rng = np.random.default_rng(1)
    d, e = _unit(rng, 2)
    train = _features(np.array([[100.0, 100.0], [105.0, 100.0]]), np.vstack([d + 0.1 * e, d - 0.1 * e]))
    query = _features(np.array([[10.0, 10.0]]), d[None])
    predicted = np.array([[102.0, 100.0]])
    assert len(guided_matches(query, predicted, train, train.keypoints, 20.0, ratio=0.9)) == 0
    assert len(guided_matches(query, predicted, train, train.keypoints, 20.0, ratio=1.0)) == 1


def test_two_frame_keypoints_wanting_one_map_keypoint_leave_it_to_the_nearer() -> None:
    rng = np.random.default_rng(2)
    d = _unit(rng, 1)
    train = _features(np.array([[100.0, 100.0]]), d)
    near = d + 0.01 * _unit(rng, 1)
    far = d + 0.3 * _unit(rng, 1)
    query = _features(np.array([[0.0, 0.0], [5.0, 5.0]]), np.vstack([far, near]))
    m = guided_matches(query, np.array([[101.0, 100.0], [99.0, 100.0]]), train, train.keypoints, 20.0)
    np.testing.assert_array_equal(m.pairs, [[1, 0]])


def test_binary_descriptors_are_compared_by_hamming_distance() -> None:
    rng = np.random.default_rng(4)
    bits = rng.integers(0, 256, (50, 32), dtype=np.uint8)
    points = rng.uniform(0, SIZE, (50, 2))
    flipped = bits.copy()
    flipped[:, 0] ^= 0b11  # two bits of 256 differ
    m = guided_matches(_features(points, flipped), points, _features(points, bits), points, 40.0)
    assert len(m) >= 45
    np.testing.assert_array_equal(m.pairs[:, 0], m.pairs[:, 1])
    assert np.all(m.distances == 2.0)


def test_empty_inputs_and_a_prediction_per_keypoint(scene) -> None:
    query, predicted, train, _ = scene
    assert (
        len(guided_matches(query.subset(np.array([], int)), predicted[:0], train, train.keypoints, 20.0)) == 0
    )
    far = np.full_like(predicted, -1000.0)
    assert len(guided_matches(query, far, train, train.keypoints, 20.0)) == 0
    with pytest.raises(OrthonavError, match="one predicted position per keypoint"):
        guided_matches(query, predicted[:10], train, train.keypoints, 20.0)
