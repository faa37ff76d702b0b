"""Feature backends: registry, config validation, masks, rotation-invariant matching, empty sets."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from helpers_geotiff import textured

from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet, Matches, available_backends, create_backend

BACKENDS = ["orb", "sift"]
EXPECTED_DESCRIPTORS = {"orb": (32, np.uint8), "sift": (128, np.float32)}


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    """A 480 x 480 textured grayscale image."""
    return textured(480, 480, bands=1, seed=4)[0]


def test_registry_lists_orb_and_sift() -> None:
    """Both classical backends are registered and creatable by name."""
    names = available_backends()
    assert {"orb", "sift"} <= set(names)
    assert names == sorted(names)
    for name in BACKENDS:
        assert create_backend(name).name == name


def test_unknown_backend_is_refused() -> None:
    """An unknown name raises OrthonavError listing what is available."""
    with pytest.raises(OrthonavError, match=r"unknown feature backend 'surf'.*orb.*sift"):
        create_backend("surf")


@pytest.mark.parametrize("name", BACKENDS)
def test_unknown_option_is_refused(name: str) -> None:
    """A typo in the config raises OrthonavError naming the option and the known ones."""
    with pytest.raises(OrthonavError, match=r"unknown option\(s\) \['max_keypoint'\].*max_keypoints"):
        create_backend(name, max_keypoint=100)


def test_options_override_defaults() -> None:
    """Config overrides take effect: fewer keypoints requested, fewer found."""
    backend = create_backend("orb", max_keypoints=100)
    assert backend.conf["max_keypoints"] == 100
    assert backend.conf["ratio"] == create_backend("orb").conf["ratio"]
    assert 0 < len(backend.extract(textured(256, 256, bands=1)[0])) <= 100


@pytest.mark.parametrize("name", BACKENDS)
def test_features_respect_mask(name: str, image: np.ndarray) -> None:
    """With a mask, every keypoint lies inside the allowed rectangle (to pyramid-level rounding)."""
    backend = create_backend(name)
    col0, row0, col1, row1 = 150, 100, 400, 300
    tol = 2.0  # keypoints found on coarse pyramid levels are placed to about a pixel

    def inside(kp: np.ndarray) -> np.ndarray:
        return (
            (kp[:, 0] >= col0 - tol)
            & (kp[:, 0] <= col1 + tol)
            & (kp[:, 1] >= row0 - tol)
            & (kp[:, 1] <= row1 + tol)
        )

    everywhere = backend.extract(image)
    assert np.count_nonzero(~inside(everywhere.keypoints)) > 50, "unmasked, keypoints lie all over"
    mask = np.zeros_like(image)
    mask[row0:row1, col0:col1] = 255
    features = backend.extract(image, mask)
    assert len(features) > 20
    assert np.all(inside(features.keypoints))


@pytest.mark.parametrize("name", BACKENDS)
def test_feature_set_layout(name: str, image: np.ndarray) -> None:
    """Keypoints (N, 2) float32 inside the image, descriptors (N, D) of the backend's type, scores (N,)."""
    backend = create_backend(name)
    features = backend.extract(image)
    size, dtype = EXPECTED_DESCRIPTORS[name]
    n = len(features)
    assert n > 100
    assert features.keypoints.shape == (n, 2) and features.keypoints.dtype == np.float32
    assert features.descriptors.shape == (n, size) and features.descriptors.dtype == dtype
    assert features.scores.shape == (n,) and features.scores.dtype == np.float32
    assert np.all((features.keypoints >= 0) & (features.keypoints < 480))
    sub = features.subset(np.arange(0, n, 2))
    assert len(sub) == (n + 1) // 2
    np.testing.assert_array_equal(sub.descriptors[1], features.descriptors[2])


def test_the_strongest_keep_their_order() -> None:
    """``limit`` best-scored features in their extraction order, ties to the first."""
    scores = np.array([0.1, 0.9, 0.5, 0.9, 0.2, 0.7], np.float32)
    n = len(scores)
    features = FeatureSet(
        np.arange(2 * n, dtype=np.float32).reshape(n, 2), np.eye(n, dtype=np.float32), scores, (64, 48)
    )
    strongest = features.strongest(3)
    np.testing.assert_array_equal(strongest.descriptors.argmax(axis=1), [1, 3, 5])
    assert strongest.image_size == (64, 48)
    np.testing.assert_array_equal(features.strongest(4).scores, scores[[1, 2, 3, 5]])
    assert features.strongest(None) is features and features.strongest(n) is features


@pytest.mark.parametrize("name", BACKENDS)
def test_a_backend_without_a_cheaper_way_keeps_the_strongest_it_extracts(
    name: str, image: np.ndarray
) -> None:
    backend = create_backend(name)
    want = backend.extract(image).strongest(50)
    got = backend.extract_strongest(image, None, 50)
    assert len(got) == 50
    np.testing.assert_array_equal(got.keypoints, want.keypoints)
    np.testing.assert_array_equal(got.descriptors, want.descriptors)


@pytest.mark.parametrize("name", BACKENDS)
def test_matching_survives_rotation_and_brightness(name: str, image: np.ndarray) -> None:
    """Against a 30 deg rotated, darker, offset copy, most matches agree with the known rotation."""
    rotation = cv2.getRotationMatrix2D((240.0, 240.0), 30.0, 1.0)
    warped = cv2.warpAffine(
        image, rotation, (480, 480), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
    )
    warped = np.clip(warped.astype(np.float32) * 0.7 + 30.0, 0, 255).astype(np.uint8)
    backend = create_backend(name)
    query, train = backend.extract(image), backend.extract(warped)
    matches = backend.match(query, train)
    assert len(matches) >= 50
    assert matches.pairs.shape == (len(matches), 2) and matches.distances.shape == (len(matches),)
    assert np.all(np.diff(matches.distances) >= 0), "matches must come best first"
    assert len(np.unique(matches.pairs[:, 0])) == len(matches)
    predicted = query.keypoints[matches.pairs[:, 0]] @ rotation[:, :2].T + rotation[:, 2]
    error = np.linalg.norm(predicted - train.keypoints[matches.pairs[:, 1]], axis=1)
    assert np.mean(error < 3.0) > 0.8


@pytest.mark.parametrize("name", BACKENDS)
def test_unrelated_images_match_poorly(name: str, image: np.ndarray) -> None:
    """Two different textures give matches inconsistent with any single rotation: few agree."""
    backend = create_backend(name)
    other = textured(480, 480, bands=1, seed=99)[0]
    query, train = backend.extract(image), backend.extract(other)
    matches = backend.match(query, train)
    rotation = cv2.getRotationMatrix2D((240.0, 240.0), 30.0, 1.0)
    predicted = query.keypoints[matches.pairs[:, 0]] @ rotation[:, :2].T + rotation[:, 2]
    error = np.linalg.norm(predicted - train.keypoints[matches.pairs[:, 1]], axis=1)
    assert np.count_nonzero(error < 3.0) <= 0.1 * len(matches) + 2


@pytest.mark.parametrize("name", BACKENDS)
def test_uniform_image_gives_empty_set_of_right_shape(name: str) -> None:
    """No texture, no features: an empty FeatureSet with (0, D) descriptors of the right dtype."""
    backend = create_backend(name)
    features = backend.extract(np.full((200, 200), 128, np.uint8))
    size, dtype = EXPECTED_DESCRIPTORS[name]
    assert isinstance(features, FeatureSet) and len(features) == 0
    assert features.keypoints.shape == (0, 2) and features.keypoints.dtype == np.float32
    assert features.descriptors.shape == (0, size) and features.descriptors.dtype == dtype
    assert features.scores.shape == (0,)
    assert backend.empty().descriptors.shape == (0, size)


@pytest.mark.parametrize("name", BACKENDS)
def test_matching_empty_sets_gives_no_matches(name: str, image: np.ndarray) -> None:
    """Matching against an empty set returns an empty Matches with (0, 2) pairs."""
    backend = create_backend(name)
    matches = backend.match(backend.extract(image), backend.empty())
    assert isinstance(matches, Matches) and len(matches) == 0
    assert matches.pairs.shape == (0, 2)
