"""Key objects of the multi-camera SLAM paper: the contrast test, relative descriptors, two-stage
identification (on a real drone photo turned by a known rotation), lines and their matching,
colour classes and the base viewpoint of the map model."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import SHARED_DATA

from orthonav.errors import OrthonavError
from orthonav.keyobjects import (
    CLASSES,
    KeyObjectCloud,
    KeyObjectMap,
    LowLevelConfig,
    classify,
    detect_lines,
    extremal_points,
    identify,
    line_descriptors,
    match_lines,
    region_map,
    regions,
    relative_descriptors,
    segments_agree,
    transform_segments,
)

PHOTO = SHARED_DATA / "brighton_beach" / "images" / "DJI_0031.JPG"


def _photo(width: int = 800) -> np.ndarray:
    if not PHOTO.is_file():
        pytest.skip(f"real drone photos not available: {PHOTO} is missing")
    image = cv2.imread(str(PHOTO))
    return cv2.resize(
        image, (width, round(image.shape[0] * width / image.shape[1])), interpolation=cv2.INTER_AREA
    )


def test_extrema_must_pass_the_local_contrast_test():
    gray = np.full((64, 64), 100, np.uint8)
    gray[20, 20] = 200  # a strong bright spot
    gray[40, 40] = 104  # an extremum of too little contrast
    found = extremal_points(gray, LowLevelConfig(contrast_threshold=5.0))
    assert [20, 20] in found.astype(int).tolist()
    assert [40, 40] not in found.astype(int).tolist()


def test_relative_descriptors_survive_rotation_and_scale():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 500, (80, 2))
    angle = np.radians(37.0)
    rot = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    moved = 1.7 * points @ rot.T + [30.0, -12.0]
    np.testing.assert_allclose(
        relative_descriptors(points, points, 5), relative_descriptors(moved, moved, 5), atol=1e-4
    )
    with pytest.raises(OrthonavError, match="anchor points"):
        relative_descriptors(points[:3], points[:3], 5)


def test_two_stage_identification_on_a_rotated_drone_photo():
    gray = cv2.cvtColor(_photo(), cv2.COLOR_BGR2GRAY)
    h, w = gray.shape
    warp = cv2.getRotationMatrix2D((w / 2, h / 2), 15.0, 1.0)
    turned = cv2.warpAffine(gray, warp, (w, h))
    obj1, obj2, found = identify(gray, turned)
    assert len(found.gradient_pairs) >= 10
    assert len(found.extremal_pairs) >= 100  # stage 2 adds many more objects than stage 1
    p1 = obj1.extremal[found.extremal_pairs[:, 0]]
    p2 = obj2.extremal[found.extremal_pairs[:, 1]]
    err = np.linalg.norm(np.column_stack([p1, np.ones(len(p1))]) @ warp.T - p2, axis=1)
    assert np.mean(err < 3.0) > 0.7


def test_lines_are_few_and_described():
    gray = cv2.cvtColor(_photo(), cv2.COLOR_BGR2GRAY)
    segments = detect_lines(gray)
    assert 10 <= len(segments) <= 1000
    length = np.hypot(segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1])
    assert length.min() >= 20.0 and np.all(np.diff(length) <= 1e-3)  # longest first
    assert line_descriptors(segments).shape == (len(segments), 2 + 2 * 4)


def test_colour_classes_of_known_colours():
    patches = {
        "water": (120, 60, 20),
        "vegetation": (40, 160, 60),
        "built": (150, 150, 150),
        "bare_soil": (90, 140, 190),
    }
    image = np.zeros((100, 400, 3), np.uint8)
    for i, bgr in enumerate(patches.values()):
        image[:, i * 100 : (i + 1) * 100] = bgr
    labels = classify(image)
    for i, name in enumerate(patches):
        assert CLASSES[labels[50, i * 100 + 50]] == name
    assert {r.label for r in regions(labels)} == set(patches)
    with pytest.raises(OrthonavError, match="BGR"):
        classify(image[..., 0])


def test_segments_agree_by_endpoints_and_angle():
    reference = np.array([[0, 0, 100, 0], [0, 50, 100, 50]], np.float32)
    other = np.array([[101, 1, 1, -1], [0, 50, 60, 50], [0, 58, 100, 58]], np.float32)
    agree = segments_agree(reference, other, endpoint_px=3.0, angle_deg=5.0)
    assert agree.tolist() == [[True, False, False], [False, False, False]]  # reversed ends agree


def test_lines_match_across_a_rotation_of_a_drone_photo():
    gray = cv2.cvtColor(_photo(1280), cv2.COLOR_BGR2GRAY)
    h, w = gray.shape
    warp = cv2.getRotationMatrix2D((w / 2, h / 2), 10.0, 1.0)
    turned = cv2.warpAffine(gray, warp, (w, h))
    seg1, seg2 = detect_lines(gray), detect_lines(turned)
    pairs = match_lines(seg1, line_descriptors(seg1), seg2, line_descriptors(seg2))
    assert len(pairs) >= 5
    # Checked against the true rotation, not only the fitted one.
    moved = transform_segments(seg1[pairs[:, 0]], warp).reshape(-1, 2, 2)
    err = np.linalg.norm(moved - seg2[pairs[:, 1]].reshape(-1, 2, 2), axis=2)
    err = np.minimum(
        err.max(axis=1),
        np.linalg.norm(moved - seg2[pairs[:, 1]].reshape(-1, 2, 2)[:, ::-1], axis=2).max(axis=1),
    )
    assert np.mean(err < 4.0) > 0.9


def test_region_map_links_pixels_to_regions():
    image = np.zeros((100, 300, 3), np.uint8)
    image[:, :100] = (120, 60, 20)  # water
    image[:, 100:] = (40, 160, 60)  # vegetation, the larger region
    found, ids = region_map(classify(image))
    assert [r.label for r in found] == ["vegetation", "water"]
    assert ids[50, 250] == 0 and ids[50, 20] == 1


def _cloud(n: int, detector: str = "gradient") -> KeyObjectCloud:
    return KeyObjectCloud(np.arange(3 * n, dtype=float).reshape(n, 3), [detector] * n, [np.zeros(4)] * n)


def test_base_viewpoint_sees_the_most_key_objects_over_all_directions(tmp_path):
    model = KeyObjectMap()
    model.add(0, "nadir", 1, _cloud(50))  # viewpoint 1 sees most in one direction...
    model.add(0, "front", 1, _cloud(0))
    model.add(0, "nadir", 2, _cloud(30))  # ...viewpoint 2 most over both directions
    model.add(0, "front", 2, _cloud(30, "line"))
    model.origins[0] = np.zeros(4)
    assert model.base_viewpoint(0) == 2
    assert set(model.base_clouds(0)) == {"nadir", "front"}
    model.save(tmp_path / "map.npz")
    loaded = KeyObjectMap.load(tmp_path / "map.npz")
    assert loaded.summary() == model.summary()
    np.testing.assert_allclose(loaded.clouds[(0, "nadir", 1)].xyz, model.clouds[(0, "nadir", 1)].xyz)
    with pytest.raises(OrthonavError, match="no clouds"):
        model.base_viewpoint(7)
    with pytest.raises(OrthonavError, match="one of each"):
        KeyObjectCloud(np.zeros((2, 3)), ["line"], [np.zeros(2)])
    with pytest.raises(OrthonavError, match="not a key object map"):
        KeyObjectMap.load(tmp_path / "missing.npz")


def test_cloud_subset_keeps_region_links():
    cloud = KeyObjectCloud(
        np.zeros((4, 3)), ["region", "region", "gradient", "line"], [np.zeros(2)] * 4, [0, 1, 1, 0]
    )
    kept = cloud.subset(np.array([False, True, True, True]))
    assert kept.region.tolist() == [0, 0, -1]  # region 1 is now index 0; region 0 was dropped
