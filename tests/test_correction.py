"""INS drift correction by dense correlation (``orthonav.localize.dense``) on real NAIP imagery.

Every check is against geometry known independently of the corrector: frames rendered with
``orthonav.frames.render_frame`` at a known true pose, priors offset from it by a known vector,
heading and altitude errors of known sign and size, and synthetic heatmaps whose maximum is
placed by construction. The CNN parts use untrained torchvision trunks (no download).
Runs on a 2-core CPU in about 15 s.
"""

from __future__ import annotations

import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
import rasterio.windows
from conftest import CAMERA, SHARED_DATA, angle_diff_deg, naip_path
from typer.testing import CliRunner

from orthonav.bench.localize import centre_point
from orthonav.camera import CameraPose, project_points
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, ViewGeometry, make_views, render_frame
from orthonav.geo import GeoRaster, LocalFrame, destination, distance_m
from orthonav.localize import CorrectionConfig, Corrector
from orthonav.localize.dense import rivals_covariance_m2
from orthonav.models.heatmap import (
    Correlator,
    Heatmap,
    Template,
    find_peak,
    gradient_magnitude,
    ncc_heatmap,
    ncc_score,
    orientation_field,
    rival_peaks,
    root_gradient,
)
from orthonav.types import Fix, Prior

ALT_M = 600.0  # 640 x 480 px, 60 deg: a 693 x 520 m footprint, ~140 x 100 pixels of the 5 m/px map
CENTRE_PX = (467.0, 362.0)  # the middle of the NAIP quarter-quad (934 x 723 px)
PRIOR_ERROR_M = 30.0
PRIOR_ERROR_AZIMUTH_DEG = 40.0
REJECTION_WORDS = ("peak ratio", "border", "match score")

runner = CliRunner()


# --- fixtures and helpers --------------------------------------------------------------------


@pytest.fixture(scope="module")
def naip2018() -> GeoRaster:
    with GeoRaster(naip_path("20180716")) as raster:
        yield raster


@pytest.fixture(scope="module")
def corrector(naip_raster: GeoRaster) -> Corrector:
    """The classical (gradient) corrector over the 2020 map."""
    return Corrector(naip_raster, CAMERA)


def pose_at(
    raster: GeoRaster, col: float, row: float, yaw: float, pitch=0.0, roll=0.0, alt=ALT_M
) -> TruePose:
    lat, lon = raster.pixel_to_latlon(col, row)
    return TruePose(float(lat), float(lon), alt, yaw, pitch, roll)


def offset_prior(pose: TruePose, **kwargs) -> Prior:
    """A prior 30 m from the truth at azimuth 40 deg, with the true altitude, heading and attitude."""
    lat, lon = destination(pose.lat, pose.lon, PRIOR_ERROR_AZIMUTH_DEG, PRIOR_ERROR_M)
    fields = {
        "alt_agl_m": pose.alt_agl_m,
        "heading_deg": pose.yaw_deg,
        "pitch_deg": pose.pitch_deg,
        "roll_deg": pose.roll_deg,
        "heading_sigma_deg": 2.0,
    }
    return Prior(lat, lon, **{**fields, **kwargs})


def error_m(fix: Fix, pose: TruePose) -> float:
    return float(distance_m(fix.pose.lat, fix.pose.lon, pose.lat, pose.lon))


def centre_error_m(fix: Fix, pose: TruePose) -> float:
    """How far the fix put the ground point under the image centre (inf without a pose)."""
    if fix.pose is None:
        return math.inf
    return float(distance_m(*centre_point(CAMERA, pose), fix.pose.centre_lat, fix.pose.centre_lon))


def gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


def assert_rejected(fix: Fix) -> None:
    assert not fix.accepted, fix.quality
    assert any(word in fix.reason for word in REJECTION_WORDS), fix.reason
    assert fix.pose is None and fix.covariance_enu_m2 is None
    record = fix.to_dict()
    assert record["lat"] is None and record["lon"] is None


# --- views: geometry -------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("heading", "east", "north"),
    [(0.0, (1, 0), (0, -1)), (90.0, (0, -1), (-1, 0)), (180.0, (-1, 0), (0, 1)), (270.0, (0, 1), (1, 0))],
)
def test_heading_up_offsets_to_east_north(heading: float, east: tuple, north: tuple) -> None:
    """Image right is the heading + 90 deg, image up the heading: one metre east/north by hand."""
    geometry = ViewGeometry(47.0, -99.0, heading, 2.0, (0.0, 0.0), (100, 80), (150, 120))
    # (dx, dy) px for one gsd east and one gsd north, from the heading by hand (y down)
    for (dx, dy), want in ((east, (2.0, 0.0)), (north, (0.0, 2.0))):
        assert np.allclose(geometry.offset_to_en(dx, dy), want, atol=1e-9)
    # pixels_to_en: the view's centre pixel is its ground centre point
    centred = ViewGeometry(47.0, -99.0, heading, 2.0, (5.0, -7.0), (100, 80), (150, 120))
    assert np.allclose(centred.pixels_to_en(np.array([[75.0, 60.0]]), (150, 120)), [[5.0, -7.0]])


@pytest.mark.parametrize("heading", [0.0, 75.0, 160.0, 250.0])
@pytest.mark.parametrize("attitude", [(0.0, 0.0), (4.0, -3.0)], ids=["level", "pitch4-roll-3"])
def test_frame_view_lies_in_the_region_where_the_prior_error_puts_it(
    naip_raster: GeoRaster, heading: float, attitude: tuple[float, float]
) -> None:
    """Same-date frame, prior 30 m off at azimuth 40: the frame view's content is found in the
    region view at the pixel offset computed by hand from that vector and the heading."""
    pose = pose_at(naip_raster, *CENTRE_PX, heading, *attitude)
    frame = render_frame(naip_raster, CAMERA, pose)
    views = make_views(naip_raster, CAMERA, frame, offset_prior(pose), 224, 1.5)
    w, h = views.geometry.frame_size
    rw, rh = views.geometry.region_size
    footprint_w = 2.0 * ALT_M * math.tan(math.radians(30.0))
    assert views.geometry.gsd_m == pytest.approx(footprint_w / 224, rel=1e-6)
    assert (w, h) == (224, 168) and views.frame.shape == (h, w, 3) and views.region.shape == (rh, rw, 3)
    assert views.region_mask.all()  # well inside the map
    # The truth relative to the prior: 30 m towards azimuth 220 deg; into heading-up pixels.
    t = math.radians(PRIOR_ERROR_AZIMUTH_DEG + 180.0)
    east, north = PRIOR_ERROR_M * math.sin(t), PRIOR_ERROR_M * math.cos(t)
    hd = math.radians(heading)
    right, forward = east * math.cos(hd) - north * math.sin(hd), east * math.sin(hd) + north * math.cos(hd)
    want = np.array([right, -forward]) / views.geometry.gsd_m
    # Where the (fully seen) middle of the frame view lies in the region, by plain gray correlation.
    x0, y0 = w // 5, h // 5
    inner = gray(views.frame)[y0 : h - y0, x0 : w - x0]
    assert views.frame_mask[y0 : h - y0, x0 : w - x0].all()
    scores = cv2.matchTemplate(gray(views.region), inner, cv2.TM_CCOEFF_NORMED)
    _, best, _, (x, y) = cv2.minMaxLoc(scores)
    found = np.array([x - x0 - (rw - w) / 2, y - y0 - (rh - h) / 2])
    assert best > 0.8
    assert np.abs(found - want).max() <= 1.0, (found, want)


def test_onto_level_terrain_the_frame_view_is_the_flat_one(naip_raster: GeoRaster) -> None:
    """Terrain of one height everywhere is flat ground: the view sampled point by point onto it
    is the view warped onto the plane (the same pixel conventions)."""
    pose = pose_at(naip_raster, *CENTRE_PX, 40.0, 3.0, -2.0)
    frame = render_frame(naip_raster, CAMERA, pose)
    prior = offset_prior(pose)
    flat = make_views(naip_raster, CAMERA, frame, prior, 224, 1.5)
    level = make_views(
        naip_raster, CAMERA, frame, prior, 224, 1.5, lambda lat, lon: np.full(np.shape(lat), 312.0)
    )
    both = flat.frame_mask & level.frame_mask
    assert both.mean() > 0.9 and (flat.frame_mask ^ level.frame_mask).mean() < 0.01
    diff = np.abs(gray(flat.frame) - gray(level.frame))[both]
    assert np.median(diff) < 1.0 and np.percentile(diff, 99) < 12.0


def test_onto_the_terrain_a_raised_point_lies_where_it_stands(naip_raster: GeoRaster) -> None:
    """A bright mark 60 m above the ground, 230 m from below the camera at 600 m: flat ground
    puts it 26 m further out (8 view pixels); the terrain view puts it at its place."""
    pose = pose_at(naip_raster, *CENTRE_PX, 30.0)
    prior = Prior(pose.lat, pose.lon, ALT_M, 30.0, 0.0, 0.0, heading_sigma_deg=2.0)
    mark_en, raised_m = np.array([200.0, 120.0]), 60.0
    camera_pose = CameraPose(0.0, 0.0, ALT_M, 30.0, 0.0, 0.0)
    u, v = project_points(CAMERA, camera_pose, np.array([[*mark_en, raised_m]]))[0]
    frame = np.zeros((CAMERA.height, CAMERA.width, 3), np.uint8)
    cv2.circle(frame, (round(u - 0.5), round(v - 0.5)), 6, (255, 255, 255), -1)
    local = LocalFrame(pose.lat, pose.lon)

    def heights(lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        east, north = local.to_enu(lat, lon)
        # A plateau: no ground behind the mark that the raised surface would hide.
        return np.where(np.hypot(east - mark_en[0], north - mark_en[1]) < 60.0, raised_m, 0.0)

    geometry = make_views(naip_raster, CAMERA, frame, prior, 224, 1.5).geometry
    dx, dy = geometry.en_to_offset(*(mark_en - geometry.centre_en))
    want = np.array([dx, dy]) + np.array(geometry.frame_size) / 2.0
    found = {}
    for name, terrain in (("flat", None), ("terrain", heights)):
        views = make_views(naip_raster, CAMERA, frame, prior, 224, 1.5, terrain)
        rows, cols = np.nonzero(gray(views.frame) > 128)
        found[name] = np.hypot(cols.mean() + 0.5 - want[0], rows.mean() + 0.5 - want[1])
    assert found["terrain"] < 1.0 and found["flat"] > 6.0, found


def test_the_corrector_orthorectifies_onto_its_map_terrain(naip_raster: GeoRaster) -> None:
    """Without a package with a terrain model, flat ground, and the fix says so."""
    pose = pose_at(naip_raster, *CENTRE_PX, 0.0)
    fix = Corrector(naip_raster, CAMERA).localize(render_frame(naip_raster, CAMERA, pose), offset_prior(pose))
    assert fix.accepted and fix.quality["terrain"] == 0.0


@pytest.mark.parametrize("heading", [0.0, 75.0, 160.0, 250.0])
@pytest.mark.parametrize("attitude", [(0.0, 0.0), (4.0, -3.0)], ids=["level", "pitch4-roll-3"])
def test_same_date_correction_moves_the_estimate_back(
    naip_raster: GeoRaster, corrector: Corrector, heading: float, attitude: tuple[float, float]
) -> None:
    pose = pose_at(naip_raster, *CENTRE_PX, heading, *attitude)
    frame = render_frame(naip_raster, CAMERA, pose)
    prior = offset_prior(pose)
    assert float(distance_m(prior.lat, prior.lon, pose.lat, pose.lon)) == pytest.approx(PRIOR_ERROR_M)
    fix = corrector.correct(frame, prior).fix
    assert fix.accepted, fix.reason
    assert error_m(fix, pose) < 3.0
    assert fix.quality["offset_m"] == pytest.approx(PRIOR_ERROR_M, abs=3.0)
    assert angle_diff_deg(fix.pose.heading_deg, heading) < 1.0
    assert (fix.pose.pitch_deg, fix.pose.roll_deg) == attitude  # taken from the prior (the AHRS)


def test_turned_view_sign_matches_a_heading_error(naip_raster: GeoRaster) -> None:
    """Prior heading 6 deg clockwise of the truth: the frame view turned by -6 deg (not +6)
    matches the region's centre, where the exact prior position puts it."""
    pose = pose_at(naip_raster, *CENTRE_PX, 120.0)
    frame = render_frame(naip_raster, CAMERA, pose)
    prior = Prior(pose.lat, pose.lon, ALT_M, pose.yaw_deg + 6.0, 0.0, 0.0)
    views = make_views(naip_raster, CAMERA, frame, prior, 224, 1.5)
    w, h = views.geometry.frame_size
    rw, rh = views.geometry.region_size
    centre = gray(views.region)[(rh - h) // 2 : (rh + h) // 2, (rw - w) // 2 : (rw + w) // 2]
    inner = (slice(h // 5, h - h // 5), slice(w // 5, w - w // 5))  # seen at every turn
    score = {t: ncc(gray(views.turned(t).frame)[inner], centre[inner]) for t in (-6.0, 0.0, 6.0)}
    assert views.turned(-6.0).turn_deg == -6.0 and views.turned(0.0) is views
    assert score[-6.0] > 0.9 > score[0.0] > score[6.0], score


@pytest.mark.parametrize("error_deg", [6.0, -6.0])
def test_heading_error_is_recovered_in_the_fix(
    naip_raster: GeoRaster, corrector: Corrector, error_deg: float
) -> None:
    pose = pose_at(naip_raster, 430.0, 330.0, 300.0, 2.0, 1.0)
    frame = render_frame(naip_raster, CAMERA, pose)
    prior = offset_prior(pose, heading_deg=pose.yaw_deg + error_deg, heading_sigma_deg=5.0)
    fix = corrector.correct(frame, prior).fix
    assert fix.accepted, fix.reason
    assert angle_diff_deg(fix.pose.heading_deg, pose.yaw_deg) < 1.0
    assert fix.quality["heading_change_deg"] == pytest.approx(-error_deg, abs=1.0)
    assert error_m(fix, pose) < 3.0


# --- heatmap ---------------------------------------------------------------------------------


def _grid(shape=(40, 60)) -> tuple[np.ndarray, np.ndarray]:
    return np.mgrid[: shape[0], : shape[1]].astype(np.float64)


def test_find_peak_is_exact_on_a_paraboloid() -> None:
    rows, cols = _grid()
    values = 5.0 - 0.03 * ((rows - 17.3) ** 2 + (cols - 41.62) ** 2)
    peak = find_peak(Heatmap(values.astype(np.float32), 1), 5.0)
    assert (peak.row, peak.col) == pytest.approx((17.3, 41.62), abs=1e-3)
    assert peak.score == pytest.approx(values.max(), abs=1e-5)


@pytest.mark.parametrize("centre", [(12.5, 30.0), (20.2, 8.8), (27.9, 44.35)])
def test_find_peak_subcell_on_a_gaussian(centre: tuple[float, float]) -> None:
    rows, cols = _grid()
    values = np.exp(-((rows - centre[0]) ** 2 + (cols - centre[1]) ** 2) / (2 * 2.5**2))
    peak = find_peak(Heatmap(values.astype(np.float32), 1), 5.0)
    # a whole-cell answer would be off by 0.2 to 0.5 cell in at least one axis here
    assert abs(peak.row - centre[0]) < 0.08 and abs(peak.col - centre[1]) < 0.08


def test_placements_off_the_map_are_no_peak_and_a_peak_beside_them_is_on_the_border() -> None:
    """A region reaching past the map's edge: placements of the frame off the map hold the
    median of those on it (no peak there, the background unchanged); a peak next to one may
    have its truth beyond, as a peak on the heatmap's border."""
    rows, cols = _grid()
    values = np.exp(-((rows - 20) ** 2 + (cols - 30) ** 2) / 8.0).astype(np.float32)
    values[:, 40:] = 2.0  # the frame over the filled ground off the map
    on_map = np.ones(values.shape, bool)
    on_map[:, 40:] = False
    kept = Heatmap(values, 1).keep_on_map(on_map)
    assert np.all(kept.values[:, 40:] == np.median(values[:, :40]))
    peak = find_peak(kept, 5.0)
    assert (round(peak.row), round(peak.col)) == (20, 30)
    assert not kept.on_border(peak.row, peak.col)
    on_map[:, 31:] = False
    assert Heatmap(values, 1).keep_on_map(on_map).on_border(peak.row, peak.col)
    assert Heatmap(values, 1).keep_on_map(np.ones(values.shape, bool)).on_map is None
    # Half a cell from the first row (rounded to it): its neighbours off the map still count.
    on_map[:] = True
    on_map[0, :] = False
    assert Heatmap(values, 1).keep_on_map(on_map).on_border(0.5, 30.0)


def test_peak_ratio_and_exclusion() -> None:
    rows, cols = _grid()

    def bump(r, c, height):
        return height * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * 2.0**2))

    two = Heatmap((bump(10, 10, 1.0) + bump(30, 45, 0.5)).astype(np.float32), 1)
    peak = find_peak(two, 5.0)
    assert (round(peak.row), round(peak.col)) == (10, 10)
    assert peak.second == pytest.approx(0.5, abs=1e-3)
    assert peak.ratio == pytest.approx(2.0, abs=0.02)  # background (median) ~0
    # an exclusion wider than the two peaks' distance: the rival is gone, the ratio soars
    assert find_peak(two, 50.0).ratio > 100
    # one peak: its own flanks are not a rival beyond the exclusion, but they are within it
    one = Heatmap(bump(20, 30, 1.0).astype(np.float32), 1)
    assert find_peak(one, 12.0).ratio > 100
    assert find_peak(one, 0.5).ratio < 1.2
    # flat heatmap: nothing stands out
    assert find_peak(Heatmap(np.full((20, 20), 0.3, np.float32), 1), 3.0).ratio < 1.01


def test_rival_humps_are_the_other_local_maxima_with_their_share_of_the_peak() -> None:
    """Separate humps are rivals at their height above the background over the peak's; the
    peak's own flanks and a hump within the exclusion are not."""
    rows, cols = _grid()

    def bump(r, c, height):
        return height * np.exp(-((rows - r) ** 2 + (cols - c) ** 2) / (2 * 2.0**2))

    heatmap = Heatmap((bump(10, 10, 1.0) + bump(30, 45, 0.6) + bump(12, 14, 0.9)).astype(np.float32), 1)
    peak = find_peak(heatmap, 8.0)
    rivals = rival_peaks(heatmap, peak, 8.0)
    assert len(rivals) == 1
    floor = float(np.median(heatmap.values))
    assert tuple(rivals[0, :2]) == (30, 45)
    assert rivals[0, 2] == pytest.approx((0.6 - floor) / (peak.score - floor), abs=0.01)
    alone = Heatmap(bump(20, 30, 1.0).astype(np.float32), 1)
    assert len(rival_peaks(alone, find_peak(alone, 8.0), 8.0)) == 0


def test_a_peak_that_barely_beats_another_place_carries_that_place_in_its_covariance() -> None:
    """The covariance's spread toward another hump of the heatmap grows as it nears the peak's
    height, and is nothing where the peak stands alone."""
    geometry = ViewGeometry(0.0, 0.0, 30.0, 2.0, (0.0, 0.0), (64, 48), (128, 96))
    weight = CorrectionConfig().rival_weight
    rows, cols = _grid()
    spreads = []
    for height in (0.0, 0.5, 0.8, 0.95):
        values = np.exp(-((rows - 10) ** 2 + (cols - 10) ** 2) / 8.0)
        values += height * np.exp(-((rows - 30) ** 2 + (cols - 50) ** 2) / 8.0)
        heatmap = Heatmap(values.astype(np.float32), 1)
        rivals = rivals_covariance_m2(geometry, heatmap, find_peak(heatmap, 7.0), 7.0, weight)
        assert np.allclose(rivals, rivals.T) and np.all(np.linalg.eigvalsh(rivals) >= -1e-9)
        spreads.append(math.sqrt(np.trace(rivals)))
    apart_m = 2.0 * math.hypot(20, 40)
    assert spreads[0] == 0.0
    # Nearly as high, the other place holds nearly half the position; half as high, under a tenth.
    assert spreads == sorted(spreads) and spreads[-1] > 0.5 * apart_m
    assert spreads[1] < math.sqrt(0.1) * apart_m


def test_ncc_heatmap_with_a_mask_ignores_the_masked_template_pixels(naip_raster: GeoRaster) -> None:
    region = gradient_magnitude(naip_raster.read_rgb()[300:420, 400:560])
    x, y, w, h = 37, 21, 80, 60
    template = region[y : y + h, x : x + w].copy()
    mask = np.ones_like(template, bool)
    mask[:, : w // 3] = False
    template[~mask] = np.random.default_rng(0).uniform(0, 3 * template.max(), (~mask).sum())
    masked = ncc_heatmap(region, template, mask)
    plain = ncc_heatmap(region, template)
    assert masked.values.shape == (120 - h + 1, 160 - w + 1) and masked.stride == 1
    assert np.unravel_index(np.argmax(masked.values), masked.values.shape) == (y, x)
    assert masked.values[y, x] > 0.75
    assert masked.values[y, x] > plain.values[y, x] + 0.2
    assert masked.placement_px(y, x) == (x, y)


@pytest.mark.parametrize(("size", "template_size"), [((252, 336), (84, 112)), ((120, 160), (60, 80))])
def test_the_correlator_is_opencvs_normalised_correlation(
    naip_raster: GeoRaster, size: tuple[int, int], template_size: tuple[int, int]
) -> None:
    """One region with several masked templates by FFT: matchTemplate's TM_CCOEFF_NORMED to float
    precision, over a region with a flat (off the map) strip and a flat template too."""
    (rows, cols), (h, w) = size, template_size
    region = gradient_magnitude(naip_raster.read_rgb()[200 : 200 + rows, 300 : 300 + cols])
    region[:, : cols // 5] = 0.0  # flat: OpenCV's rule for a window without variance
    correlator = Correlator(region, (h, w))
    rng = np.random.default_rng(1)
    for k in range(4):
        y, x = int(rng.integers(0, rows - h)), int(rng.integers(0, cols - w))
        template = region[y : y + h, x : x + w] + rng.normal(0.0, 0.1, (h, w)).astype(np.float32)
        mask = _rotated_mask(h, w, 20.0 * k) if k else np.ones((h, w), bool)
        want = ncc_heatmap(region, template, mask).values
        got = correlator.heatmap(Template(template, mask)).values
        assert got.shape == want.shape and got.dtype == np.float32
        np.testing.assert_allclose(got, want, atol=1e-4)
        assert np.argmax(got) == np.argmax(want)
    flat = np.full((h, w), 2.0, np.float32)
    np.testing.assert_allclose(
        correlator.heatmap(Template(flat)).values, ncc_heatmap(region, flat).values, atol=1e-4
    )
    with pytest.raises(ValueError, match="larger than the region"):
        Correlator(region[: h - 1], (h, w))


def test_the_correlator_takes_channels_together_as_opencv_does(naip_raster: GeoRaster) -> None:
    """Orientation fields (two channels): matchTemplate's TM_CCOEFF_NORMED of a two-channel image
    (each channel's own mean, sums over both), masked templates included; a template of another
    channel count is refused."""
    region = orientation_field(naip_raster.read_rgb()[200:320, 300:460])
    correlator = Correlator(region, (60, 80))
    rng = np.random.default_rng(4)
    for k in range(3):
        y, x = int(rng.integers(0, 60)), int(rng.integers(0, 80))
        template = region[y : y + 60, x : x + 80] + rng.normal(0.0, 0.2, (60, 80, 2)).astype(np.float32)
        mask = _rotated_mask(60, 80, 30.0 * k) if k else np.ones((60, 80), bool)
        filled = template.copy()
        filled[~mask] = template[mask].mean(axis=0)
        want = cv2.matchTemplate(region, filled, cv2.TM_CCOEFF_NORMED)
        got = correlator.heatmap(Template(template, mask)).values
        np.testing.assert_allclose(got, want, atol=1e-4)
        assert np.unravel_index(np.argmax(got), got.shape) == (y, x)
    with pytest.raises(ValueError, match="channels"):
        correlator.heatmap(Template(region[:60, :80, 0]))


def test_orientation_is_the_same_when_the_contrast_reverses(naip_raster: GeoRaster) -> None:
    """The doubled angle: an edge brighter on one side in one year and darker in the next (a
    crop turned) gives the same field; each vector's length is the square root of the gradient
    magnitude, as the magnitude correlation weighs it."""
    gray_rgb = cv2.cvtColor(naip_raster.read_rgb()[100:260, 200:400], cv2.COLOR_RGB2GRAY)
    rgb = np.dstack([gray_rgb] * 3)  # gray, so that 255 - rgb is exactly the reversed gray image
    field = orientation_field(rgb)
    assert field.shape == (160, 200, 2) and field.dtype == np.float32
    np.testing.assert_allclose(orientation_field(255 - rgb), field, atol=2e-3)  # float rounding of the blur
    np.testing.assert_allclose(
        np.hypot(field[..., 0], field[..., 1]), gradient_magnitude(rgb), rtol=1e-4, atol=1e-3
    )
    assert np.all(orientation_field(np.full((20, 30, 3), 90, np.uint8)) == 0.0)  # flat: no orientation


def test_one_placement_score_is_the_heatmaps_value(naip_raster: GeoRaster) -> None:
    """``ncc_score`` (the match score of a placed frame) is ``ncc_heatmap``'s value for a
    template of the image's size, masked or not, OpenCV's rules for flat images included."""
    image = gradient_magnitude(naip_raster.read_rgb()[100:268, 200:424])
    rng = np.random.default_rng(2)
    for angle in (0.0, 25.0):
        template = image + rng.normal(0.0, 0.3, image.shape).astype(np.float32)
        mask = _rotated_mask(*image.shape, angle) if angle else None
        want = float(ncc_heatmap(image, template, mask).values[0, 0])
        assert ncc_score(image, template, mask) == pytest.approx(want, abs=1e-5)
    flat = np.full(image.shape, 3.0, np.float32)
    assert ncc_score(image, flat) == float(ncc_heatmap(image, flat).values[0, 0]) == 1.0
    assert ncc_score(flat, image) == float(ncc_heatmap(flat, image).values[0, 0]) == 0.0
    with pytest.raises(ValueError, match="the same size"):
        ncc_score(image[:-1], image)


def test_gradients_are_the_same_every_time(naip_raster: GeoRaster) -> None:
    """The same image gives the same gradient image to the last bit, call after call (OpenCV's
    threaded cv2.magnitude did not: near-equal peaks of a lost frame's search then swapped
    between two runs of the same frame)."""
    rgb = np.ascontiguousarray(naip_raster.read_rgb()[100:352, 200:536])
    first = gradient_magnitude(rgb)
    assert all(np.array_equal(first, gradient_magnitude(rgb.copy())) for _ in range(100))
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gx, gy = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    np.testing.assert_allclose(root_gradient(gray), np.sqrt(np.hypot(gx, gy)), rtol=1e-6)


def _rotated_mask(h: int, w: int, angle: float) -> np.ndarray:
    box = cv2.boxPoints(((w / 2, h / 2), (0.8 * w, 0.7 * h), angle))
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(box).astype(np.int32), 1)
    return mask.astype(bool)


def test_one_frame_at_many_places_and_headings_is_corrected_as_one_at_a_time(
    naip_raster: GeoRaster, corrector: Corrector
) -> None:
    """``correct_each`` (a lost frame's search) shares the frame view, its turns and the map read
    around each place, and gives what ``correct`` gives each prior: the same views within a grey
    level, the same decisions and fixes; a prior that cannot be corrected has its error in its
    place."""
    truth = pose_at(naip_raster, *CENTRE_PX, 30.0, 1.0, -2.0)
    frame = render_frame(naip_raster, CAMERA, truth)
    base = offset_prior(truth, heading_sigma_deg=6.0)
    priors = [replace(base, heading_deg=(truth.yaw_deg + turn) % 360.0) for turn in (0.0, 40.0, -75.0, 180.0)]
    priors.append(replace(base, lat=base.lat + 0.004))  # another place
    priors.append(Prior(*destination(base.lat, base.lon, 0.0, 10_000.0), ALT_M, 30.0))  # off the map
    together = corrector.correct_each(frame, priors, 1.5)
    assert isinstance(together[-1], OrthonavError) and "outside the map" in str(together[-1])
    shared = {id(c.views.frame) for c in together[:-1]}
    assert len(shared) < len(priors) - 1  # the flat-ground frame view is made once, not per prior
    for prior, got in zip(priors[:-1], together[:-1], strict=True):
        alone = corrector.correct(frame, prior)
        for a, b in ((got.views.frame, alone.views.frame), (got.views.region, alone.views.region)):
            assert np.abs(a.astype(int) - b.astype(int)).mean() < 1.0
        assert got.fix.accepted == alone.fix.accepted, (got.fix.reason, alone.fix.reason)
        assert got.fix.quality["peak_ratio"] == pytest.approx(alone.fix.quality["peak_ratio"], rel=0.02)
        if alone.fix.accepted:
            assert (
                distance_m(got.fix.pose.lat, got.fix.pose.lon, alone.fix.pose.lat, alone.fix.pose.lon) < 0.5
            )
    assert together[0].fix.accepted and error_m(together[0].fix, truth) < 10.0
    with pytest.raises(OrthonavError, match="outside the map"):
        corrector.correct(frame, priors[-1])


# --- refinement, the fix, rejection ----------------------------------------------------------


@pytest.mark.parametrize("factor", [1.08, 0.93])
def test_ecc_recovers_an_altitude_error(naip_raster: GeoRaster, corrector: Corrector, factor: float) -> None:
    pose = pose_at(naip_raster, 500.0, 390.0, 40.0, -2.0, 3.0)
    frame = render_frame(naip_raster, CAMERA, pose)
    prior = offset_prior(pose, alt_agl_m=ALT_M * factor)
    fix = corrector.correct(frame, prior).fix
    assert fix.accepted, fix.reason
    assert fix.pose.alt_agl_m == pytest.approx(ALT_M, rel=0.015)
    assert fix.quality["scale"] == pytest.approx(1.0 / factor, rel=0.015)
    assert error_m(fix, pose) < 5.0
    # without ECC nothing measures the scale: the prior's altitude stays
    plain = Corrector(naip_raster, CAMERA, CorrectionConfig(refine="none")).correct(frame, prior).fix
    assert plain.pose.alt_agl_m == pytest.approx(ALT_M * factor)


@pytest.mark.parametrize("error_deg", [4.0, -3.0])
def test_ecc_recovers_a_heading_error_without_turns(
    naip_raster: GeoRaster, corrector: Corrector, error_deg: float
) -> None:
    """heading sigma 1 deg: no turned hypotheses are tried, ECC alone measures the rotation."""
    pose = pose_at(naip_raster, 470.0, 340.0, 200.0)
    frame = render_frame(naip_raster, CAMERA, pose)
    prior = offset_prior(pose, heading_deg=pose.yaw_deg + error_deg, heading_sigma_deg=1.0)
    correction = corrector.correct(frame, prior)
    fix = correction.fix
    assert fix.accepted, fix.reason
    assert correction.views.turn_deg == 0.0
    assert correction.alignment.rotation_deg == pytest.approx(-error_deg, abs=0.5)
    assert angle_diff_deg(fix.pose.heading_deg, pose.yaw_deg) < 0.5


def test_fix_carries_covariance_quality_and_timings(naip_raster: GeoRaster, corrector: Corrector) -> None:
    pose = pose_at(naip_raster, *CENTRE_PX, 10.0)
    fix = corrector.correct(render_frame(naip_raster, CAMERA, pose), offset_prior(pose)).fix
    assert fix.accepted and fix.method == "correction:gradient-224"
    cov = fix.covariance_enu_m2
    assert cov.shape == (2, 2) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    gsd = fix.quality["gsd_m"]
    assert fix.sigma_m >= corrector.config.sigma_px * gsd - 1e-9
    assert error_m(fix, pose) < 3 * fix.sigma_m
    for key in ("peak_ratio", "peak_score", "offset_m", "ecc_score", "scale", "match_score"):
        assert math.isfinite(fix.quality[key]), key
    assert fix.quality["peak_ratio"] >= corrector.config.min_peak_ratio
    assert set(fix.timings_ms) == {"views_ms", "correlate_ms", "refine_ms", "total_ms"}
    assert fix.timings_ms["total_ms"] >= fix.timings_ms["views_ms"] > 0
    record = json.loads(json.dumps(fix.to_dict()))
    assert record["accepted"] and record["sigma_m"] > 0 and len(record["covariance"]) == 2
    # the ground point under the image centre is the one rendered there
    assert float(distance_m(fix.pose.centre_lat, fix.pose.centre_lon, pose.lat, pose.lon)) < 3.0


def _foreign_frames() -> dict[str, np.ndarray]:
    """Frames of other places (and of nothing) for the 640 x 480 camera."""
    rng = np.random.default_rng(2024)
    frames = {f"noise{i}": rng.integers(0, 256, (480, 640, 3), dtype=np.uint8) for i in range(3)}
    frames["uniform"] = np.full((480, 640, 3), 128, np.uint8)
    for name, alt in (("nl_aerial_25cm", 150.0), ("oam_manila_10cm", 100.0)):
        path = SHARED_DATA / "highres" / f"{name}.tif"
        if path.is_file():
            with GeoRaster(path) as other:
                lat, lon = other.center_latlon
                frames[name] = render_frame(other, CAMERA, TruePose(float(lat), float(lon), alt, 30.0))
    photo = SHARED_DATA / "brighton_beach" / "images" / "DJI_0020.JPG"
    if photo.is_file():
        frames["brighton"] = cv2.resize(cv2.imread(str(photo)), (640, 480), interpolation=cv2.INTER_AREA)
    return frames


def test_frames_of_other_places_and_of_noise_are_rejected(
    naip_raster: GeoRaster, corrector: Corrector
) -> None:
    """No right answer exists in the map: every correction is rejected with its reason."""
    rng = np.random.default_rng(5)
    frames = _foreign_frames()
    assert len(frames) >= 4
    for name, frame in frames.items():
        for col, row in ((300.0, 300.0), (600.0, 420.0)):
            prior = Prior(*map(float, naip_raster.pixel_to_latlon(col, row)), ALT_M, rng.uniform(0, 360))
            fix = corrector.correct(frame, prior).fix
            assert_rejected(fix)
            if name == "uniform":
                assert "peak ratio" in fix.reason


def test_picture_of_a_rejected_correction(
    naip_raster: GeoRaster, corrector: Corrector, tmp_path: Path
) -> None:
    from orthonav.viz.correction import plot_correction

    prior = Prior(*map(float, naip_raster.pixel_to_latlon(*CENTRE_PX)), ALT_M, 10.0)
    correction = corrector.correct(np.full((480, 640, 3), 128, np.uint8), prior)
    assert not correction.fix.accepted
    out = plot_correction(correction, corrector.feature_maps(correction.views), tmp_path / "c.png", (3, 4))
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and [p.name for p in tmp_path.iterdir()] == ["c.png"]


# --- cross-date and CNN backbones ------------------------------------------------------------


def _cross_date_cases(
    map_raster: GeoRaster,
    frames_raster: GeoRaster,
    n: int,
    seed: int,
    prior_error_m: tuple[float, float] = (10.0, 15.0),
):
    """(true pose, frame, prior ``prior_error_m`` off with realistic heading/altitude errors) x n:
    the pose placed on ``map_raster``, the frame rendered from ``frames_raster`` (another date)."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        pose = pose_at(
            map_raster,
            rng.uniform(200, 734),
            rng.uniform(190, 533),
            rng.uniform(0, 360),
            rng.uniform(-3, 3),
            rng.uniform(-3, 3),
            alt=rng.uniform(500, 700),
        )
        frame = render_frame(frames_raster, CAMERA, pose, Photometric.random(rng, 0.5), rng)
        lat, lon = destination(pose.lat, pose.lon, rng.uniform(0, 360), rng.uniform(*prior_error_m))
        prior = Prior(
            lat,
            lon,
            pose.alt_agl_m * rng.uniform(0.97, 1.03),
            (pose.yaw_deg + rng.normal(0.0, 1.5)) % 360.0,
            pose.pitch_deg,
            pose.roll_deg,
            heading_sigma_deg=2.0,
        )
        yield pose, frame, prior


def test_cross_date_gradient_correction(naip2018: GeoRaster, naip_raster: GeoRaster) -> None:
    """Map 2018, frames 2020 (another season and sensor), 10-15 m prior error."""
    corrector = Corrector(naip2018, CAMERA)
    errors, before = [], []
    for pose, frame, prior in _cross_date_cases(naip2018, naip_raster, 12, seed=3):
        before.append(float(distance_m(prior.lat, prior.lon, pose.lat, pose.lon)))
        fix = corrector.correct(frame, prior).fix
        errors.append(error_m(fix, pose) if fix.accepted else math.inf)
    errors = np.array(errors)
    print(f"\ncross-date errors (m): {np.round(errors, 1).tolist()}")
    assert (errors < 10.0).sum() >= 9, errors  # a clear majority
    accepted = errors[np.isfinite(errors)]
    assert np.median(accepted) < np.median(before)
    assert accepted.max() < 40.0  # never accepted far away


def test_orientation_places_2009_frames_the_magnitude_does_not(naip_raster: GeoRaster) -> None:
    """Frames of 2009 (a wet, hazy year: ponds far larger, fields faint) on the 2020 map, priors
    40-80 m off, the gates open: the correlation peak of the gradient's orientation puts the
    frame centre within 25 m far more often than that of its magnitude (12 and 5 of 12 here)."""
    with GeoRaster(naip_path("20090818")) as naip2009:
        cases = list(_cross_date_cases(naip_raster, naip2009, 12, seed=6, prior_error_m=(40.0, 80.0)))
    placed = {}
    for backbone in ("gradient", "orientation"):
        config = CorrectionConfig(
            backbone=backbone, min_peak_ratio=1.0, min_match_score=-1.0, search_factor=1.6
        )
        corrector = Corrector(naip_raster, CAMERA, config)
        fixes = [corrector.correct(frame, prior).fix for _, frame, prior in cases]
        errors = [centre_error_m(fix, pose) for fix, (pose, _, _) in zip(fixes, cases, strict=True)]
        placed[backbone] = sum(error < 25.0 for error in errors)
    assert placed["orientation"] >= 10 and placed["orientation"] >= placed["gradient"] + 4, placed


@pytest.mark.usefixtures("torch_one_thread")
def test_untrained_cnn_trunk_runs_end_to_end(naip2018: GeoRaster, naip_raster: GeoRaster) -> None:
    """ResNet18 (random weights, stride 4): CNN heatmap -> full-resolution NCC -> ECC -> fix."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("torchvision")
    config = CorrectionConfig(backbone="resnet18")
    torch.manual_seed(0)  # random weights: the same ones every run
    same_date = Corrector(naip_raster, CAMERA, config)
    assert same_date.network.stride == 4
    for heading in (20.0, 230.0):
        pose = pose_at(naip_raster, *CENTRE_PX, heading, 2.0, -1.0)
        correction = same_date.correct(render_frame(naip_raster, CAMERA, pose), offset_prior(pose))
        fix = correction.fix
        assert fix.accepted and fix.method == "correction:resnet18-224", fix.reason
        assert error_m(fix, pose) < 3.0
        assert correction.heatmap.stride == 4
        w, h = correction.views.geometry.frame_size
        rw, rh = correction.views.geometry.region_size
        assert correction.heatmap.values.shape == ((rh - h) // 4 + 1, (rw - w) // 4 + 1)
    frame_features, region_features = same_date.feature_maps(correction.views)
    assert frame_features.shape == (64, h // 4, w // 4)
    assert region_features.shape == (64, rh // 4, rw // 4)
    torch.manual_seed(0)
    cross_date = Corrector(naip2018, CAMERA, config)
    errors = [
        error_m(fix, pose) if (fix := cross_date.correct(frame, prior).fix).accepted else math.inf
        for pose, frame, prior in _cross_date_cases(naip2018, naip_raster, 4, seed=3)
    ]
    print(f"\nresnet18 cross-date errors (m): {np.round(errors, 1).tolist()}")
    assert sum(e < 15.0 for e in errors) >= 3, errors


# --- trunks ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def trunks():
    torch = pytest.importorskip("torch")
    pytest.importorskip("torchvision")
    from orthonav.models import trunks

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield trunks
    torch.set_num_threads(before)


@pytest.mark.parametrize("backbone", ["vgg11", "resnet18", "mobilenetv2"])
def test_trunk_strides_and_unit_features_at_every_stage(trunks, backbone: str) -> None:
    import torch

    strides = trunks.ARCHITECTURES[backbone].strides
    images = torch.randn(1, 3, 64, 96)
    # The deepest cut holds every shallower one: its first k stages are the stage-k trunk.
    deepest = trunks.DenseFeatures(backbone, len(strides)).eval()
    with torch.inference_mode():
        for k, stride in enumerate(strides, start=1):
            out = deepest.trunk[:k](images)
            assert tuple(out.shape[2:]) == (64 // stride, 96 // stride), (k, stride)
    for stage in range(1, len(strides) + 1) if backbone != "vgg11" else (None,):
        net = trunks.DenseFeatures(backbone, stage).eval()
        with torch.inference_mode():
            features = net(images)
        assert net.stride == strides[net.stage - 1]
        assert tuple(features.shape[2:]) == (64 // net.stride, 96 // net.stride)
        assert torch.allclose(features.norm(dim=1), torch.ones(1, *features.shape[2:]), atol=1e-4)
    with pytest.raises(OrthonavError, match=f"{backbone} stage: expected 1..{len(strides)}"):
        trunks.DenseFeatures(backbone, len(strides) + 1)


def test_unknown_trunk_is_refused(trunks) -> None:
    with pytest.raises(OrthonavError, match="backbone 'alexnet'"):
        trunks.DenseFeatures("alexnet")
    with pytest.raises(OrthonavError, match="correction backbone 'alexnet'"):
        CorrectionConfig(backbone="alexnet")


def test_model_save_load_round_trip(trunks, tmp_path: Path) -> None:
    import torch

    torch.manual_seed(1)
    net = trunks.DenseFeatures("resnet18", 2)
    with torch.no_grad():  # BN statistics that are not the defaults, so they must travel too
        for module in net.modules():
            if isinstance(module, torch.nn.BatchNorm2d):
                module.running_mean.uniform_(-0.2, 0.2)
                module.running_var.uniform_(0.5, 2.0)
    net.eval()
    info = {"dates": ["a", "b"], "validation": {"val_top1": 0.5}}
    trunks.save_model(net, tmp_path / "m.pt", info)
    assert [p.name for p in tmp_path.iterdir()] == ["m.pt"]  # no temporary file left
    loaded, loaded_info = trunks.load_model(tmp_path / "m.pt")
    assert loaded_info == info and not loaded.training
    assert (loaded.backbone, loaded.stage, loaded.stride) == ("resnet18", 2, 8)
    # The file stores half precision: the loaded net equals the original with its weights rounded.
    rounded = trunks.DenseFeatures("resnet18", 2)
    rounded.load_state_dict(
        {k: v.half().float() if v.is_floating_point() else v for k, v in net.state_dict().items()}
    )
    rounded.eval()
    images = torch.randn(2, 3, 64, 80)
    with torch.inference_mode():
        a, b, c = loaded(images), rounded(images), net(images)
    assert torch.equal(a, b)
    assert (a - c).abs().max() < 2e-2  # and stays close to the full-precision net
    trunks.save_model(loaded, tmp_path / "again.pt", loaded_info)  # a second round trip is exact
    again, _ = trunks.load_model(tmp_path / "again.pt")
    with torch.inference_mode():
        assert torch.equal(again(images), a)


def test_wrong_model_files_are_refused_clearly(trunks, tmp_path: Path) -> None:
    import torch

    net = trunks.DenseFeatures("resnet18", 2)
    trunks.save_model(net, tmp_path / "good.pt", {})
    payload = torch.load(tmp_path / "good.pt", weights_only=True)

    def write(name: str, obj) -> Path:
        torch.save(obj, tmp_path / name)
        return tmp_path / name

    cases = {
        write("relabelled.pt", {**payload, "backbone": "mobilenetv2"}): "do not fit a mobilenetv2 trunk",
        write("other_stage.pt", {**payload, "stage": 3}): "do not fit a resnet18 trunk cut at stage 3",
        write("version.pt", {**payload, "version": 99}): "format version 99",
        write("random.pt", {"weights": torch.randn(4, 4)}): "not an orthonav correction model",
        write("tensor.pt", torch.randn(3)): "not an orthonav correction model",
        write("state_dict.pt", net.state_dict()): "not an orthonav correction model",
        tmp_path / "missing.pt": "no such correction model file",
    }
    (tmp_path / "text.pt").write_text("this is not a model\n")
    cases[tmp_path / "text.pt"] = "not a readable model file"
    (tmp_path / "cut.pt").write_bytes((tmp_path / "good.pt").read_bytes()[:2000])
    cases[tmp_path / "cut.pt"] = "not a readable model file"
    for path, fragment in cases.items():
        with pytest.raises(OrthonavError) as info:
            trunks.load_model(path)
        assert fragment in str(info.value) and str(path) in str(info.value), str(info.value)
    # through the corrector
    with pytest.raises(OrthonavError, match="not a readable model file"):
        Corrector(None, CAMERA, CorrectionConfig(backbone="trained", model_path=str(tmp_path / "text.pt")))


# --- bad input: API --------------------------------------------------------------------------


def _edge_prior(raster: GeoRaster, col: float, row: float, **kwargs) -> Prior:
    lat, lon = raster.pixel_to_latlon(col, row)
    return Prior(float(lat), float(lon), kwargs.pop("alt", ALT_M), kwargs.pop("heading", 30.0), **kwargs)


def test_bad_priors_raise_clear_errors(naip_raster: GeoRaster, corrector: Corrector) -> None:
    frame = render_frame(naip_raster, CAMERA, pose_at(naip_raster, *CENTRE_PX, 30.0))
    lat, lon = (float(v) for v in naip_raster.pixel_to_latlon(*CENTRE_PX))
    cases = [
        (Prior(*destination(lat, lon, 0.0, 10_000.0), ALT_M, 30.0), "outside the map or too near its edge"),
        (_edge_prior(naip_raster, *CENTRE_PX, alt=15_000.0), "beyond the edge of the map"),  # 17 km wide
        (_edge_prior(naip_raster, *CENTRE_PX, alt=20.0), "fly higher"),  # 23 m of ground: < 16 map px
        (Prior(lat, lon, ALT_M), "missing: heading"),
        (Prior(lat, lon, None, 30.0), "missing: altitude"),
        (Prior(None, None, ALT_M, 30.0), "missing: position"),
        (
            _edge_prior(naip_raster, *CENTRE_PX, pitch_deg=35.0, roll_deg=0.0),
            "within 30 deg of straight down",
        ),
    ]
    for prior, fragment in cases:
        with pytest.raises(OrthonavError) as info:
            corrector.correct(frame, prior)
        assert fragment in str(info.value), (fragment, str(info.value))
    for kwargs in ({"alt_agl_m": 0.0}, {"alt_agl_m": -50.0}, {"alt_agl_m": 1e6}, {"alt_agl_m": math.nan}):
        with pytest.raises(OrthonavError, match="prior altitude"):
            Prior(lat, lon, heading_deg=30.0, **kwargs)


def test_a_search_region_past_the_map_edge_is_moved_onto_the_map(
    naip_raster: GeoRaster, corrector: Corrector
) -> None:
    """A prior near the map's edge: its search region (1.5 footprints) reaches past the edge; it
    is moved inwards over ground the map has, so a frame there is corrected, and a prior right at
    the edge is a rejection or a fix, never an error."""
    truth = pose_at(naip_raster, 100.0, 362.0, 30.0)
    frame = render_frame(naip_raster, CAMERA, truth)
    lat, lon = destination(truth.lat, truth.lon, PRIOR_ERROR_AZIMUTH_DEG, PRIOR_ERROR_M)
    fix = corrector.correct(frame, Prior(lat, lon, ALT_M, 30.0)).fix
    assert fix.accepted, fix.reason
    assert distance_m(truth.lat, truth.lon, fix.pose.lat, fix.pose.lon) < 10.0
    for col, row in ((20.0, 360.0), (467.0, 700.0)):  # 100 m from the west and south edges
        corrector.correct(frame, _edge_prior(naip_raster, col, row))


def test_a_frame_on_the_map_at_its_edge_is_corrected_at_a_diagonal_heading(
    naip_raster: GeoRaster, corrector: Corrector
) -> None:
    """The search region is turned to the heading: kept wholly on the map, its corner would
    leave the map first and a frame wholly on it near the edge (heading 45 deg) would lie
    outside it. It may reach past the edge by its margin (what lies off the map masked), so the
    frame is found where it is."""
    half_px = 0.5 * (139.0 + 104.0) / math.sqrt(2.0)  # the footprint turned 45 deg: 172 px across
    for col, row in ((naip_raster.width - half_px - 2.0, 362.0), (467.0, half_px + 2.0)):
        truth = pose_at(naip_raster, col, row, 45.0)
        frame = render_frame(naip_raster, CAMERA, truth)
        fix = corrector.correct(frame, offset_prior(truth)).fix
        assert fix.accepted, fix.reason
        assert distance_m(truth.lat, truth.lon, fix.pose.lat, fix.pose.lon) < 10.0


def test_a_frame_partly_off_the_map_is_never_placed_at_the_edge(
    naip_raster: GeoRaster, corrector: Corrector, tmp_path: Path
) -> None:
    """The map cut 300 px short of the orthophoto the frames are rendered from: a frame a tenth
    off the cut map's edge is placed over what it sees of the map; a third or 45 % off, placed
    right or rejected (beyond the region's reach past the edge: a peak on its border); 60 % off
    (its prior off the map) rejected. Never placed wrongly."""
    cut = tmp_path / "cut.tif"
    keep = naip_raster.width - 300
    with rasterio.open(naip_raster.path) as src:
        window = rasterio.windows.Window(0, 0, keep, src.height)
        profile = src.profile | {"width": keep, "transform": src.window_transform(window)}
        with rasterio.open(cut, "w", **profile) as out:
            out.write(src.read(window=window))
    with GeoRaster(cut) as short:
        on_cut = Corrector(short, CAMERA)
        for off in (0.1, 0.33, 0.45, 0.6):
            truth = pose_at(naip_raster, keep - (0.5 - off) * 139.0, 362.0, 0.0)
            fix = on_cut.localize(render_frame(naip_raster, CAMERA, truth), offset_prior(truth))
            if fix.accepted or off == 0.1:  # a tenth off: what it sees of the map places it
                assert fix.accepted, fix.reason
                assert distance_m(truth.lat, truth.lon, fix.pose.lat, fix.pose.lon) < 10.0, off


@pytest.mark.parametrize(
    ("frame", "fragment"),
    [
        (np.zeros((240, 320, 3), np.uint8), "expected a 640x480 colour image"),
        (np.zeros((480, 640), np.uint8), "expected an (H, W, 3) uint8 colour image"),
        (np.zeros((480, 640, 1), np.uint8), "expected a 640x480 colour image"),
        (np.zeros((480, 640, 3), np.float32), "float32"),
        ([[0, 1], [2, 3]], "got list"),
    ],
    ids=["small", "gray", "one-channel", "float", "list"],
)
def test_bad_frames_raise_clear_errors(naip_raster: GeoRaster, corrector: Corrector, frame, fragment) -> None:
    prior = _edge_prior(naip_raster, *CENTRE_PX)
    with pytest.raises(OrthonavError) as info:
        corrector.correct(frame, prior)
    assert fragment in str(info.value)


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"refine": "bogus"}, "correction refine 'bogus'"),
        ({"size_px": 16}, "correction size"),
        ({"exclusion": 1.5}, "0 < exclusion < 1"),
        ({"min_peak_ratio": 0.5}, "min_peak_ratio >= 1"),
        ({"rival_weight": 0.0}, "rival_weight"),
    ],
)
def test_bad_correction_config(kwargs: dict, fragment: str) -> None:
    with pytest.raises(OrthonavError, match=fragment):
        CorrectionConfig(**kwargs)


@pytest.mark.parametrize("factor", [1.0, 5.0])
def test_bad_search_factor(naip_raster: GeoRaster, factor: float) -> None:
    frame = render_frame(naip_raster, CAMERA, pose_at(naip_raster, *CENTRE_PX, 30.0))
    with pytest.raises(OrthonavError, match="search factor"):
        make_views(naip_raster, CAMERA, frame, _edge_prior(naip_raster, *CENTRE_PX), 224, factor)


# --- the command line ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cli_frame(naip_raster: GeoRaster, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, TruePose]:
    pose = pose_at(naip_raster, 520.0, 300.0, 65.0, 1.5, -2.0)
    path = tmp_path_factory.mktemp("correction_cli") / "frame.png"
    assert cv2.imwrite(str(path), render_frame(naip_raster, CAMERA, pose))
    return path, pose


def _run_args(frame: Path, pose: TruePose, **options) -> list[str]:
    lat, lon = destination(pose.lat, pose.lon, 250.0, 25.0)
    values = {
        "prior": f"{lat},{lon}",
        "altitude": pose.alt_agl_m,
        "heading": pose.yaw_deg,
        "pitch": pose.pitch_deg,
        "roll": pose.roll_deg,
        **options,
    }
    args = ["correction", "run", str(naip_path("20200831")), str(frame)]
    for key, value in values.items():
        if value is not None:
            args += [f"--{key}", str(value)]
    return args


def test_cli_correction_run_json_and_plot(cli_frame, tmp_path: Path) -> None:
    frame, pose = cli_frame
    plot = tmp_path / "correction.png"
    result = runner.invoke(app, [*_run_args(frame, pose), "--json", "--plot", str(plot)])
    assert result.exit_code == 0, result.output
    record = json.loads(result.output)
    assert record["accepted"], record["reason"]
    assert float(distance_m(record["lat"], record["lon"], pose.lat, pose.lon)) < 3.0
    assert record["method"] == "correction:gradient-224" and record["sigma_m"] > 0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [p.name for p in tmp_path.iterdir()] == ["correction.png"]
    # the plain text output names the same result
    text = runner.invoke(app, _run_args(frame, pose))
    assert text.exit_code == 0 and "accepted: True" in text.output


def test_cli_correction_run_bad_inputs(cli_frame, tmp_path: Path) -> None:
    frame, pose = cli_frame
    undecodable = tmp_path / "broken.png"
    undecodable.write_bytes(b"\x89PNG\r\n\x1a\n" + b"not really" * 20)
    not_a_model = tmp_path / "model.pt"
    not_a_model.write_text("weights? no.\n")
    lat, lon = destination(pose.lat, pose.lon, 0.0, 20_000.0)
    cases = [
        (_run_args(frame, pose, prior=f"{lat},{lon}"), "outside the map or too near its edge"),
        (_run_args(frame, pose, altitude=0), "prior altitude"),
        (_run_args(frame, pose, altitude=-100), "prior altitude"),
        (_run_args(frame, pose, altitude=1e6), "prior altitude"),
        (_run_args(frame, pose, altitude=15000), "beyond the edge of the map"),
        (_run_args(frame, pose, hfov=0), "camera hfov_deg"),
        (_run_args(frame, pose, hfov=200), "camera hfov_deg"),
        (_run_args(frame, pose, width=320, height=240), "expected a 320x240 colour image"),
        (_run_args(undecodable, pose), "cannot be decoded"),
        (_run_args(tmp_path / "missing.png", pose), "no such frame file"),
        (_run_args(frame, pose, model=not_a_model), "not a readable model file"),
        (_run_args(frame, pose, backbone="alexnet"), "correction backbone 'alexnet'"),
        (_run_args(frame, pose, **{"search-factor": 9}), "search factor"),
    ]
    for args, fragment in cases:
        result = runner.invoke(app, args)
        assert isinstance(result.exception, OrthonavError), (args, result.exception, result.output)
        assert fragment in str(result.exception), (fragment, str(result.exception))
    # a required option left out: a usage error (exit 2), not a traceback
    result = runner.invoke(app, _run_args(frame, pose, heading=None))
    assert result.exit_code == 2 and isinstance(result.exception, SystemExit), result.output
    assert "--heading" in result.output


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        ({"hfov": 200}, "camera hfov_deg"),
        ({"altitude": 0}, "prior altitude"),
        ({"heading": None}, "--heading"),
    ],
    ids=["hfov", "altitude", "missing-heading"],
)
def test_console_entry_point_exits_2_without_traceback(
    cli_frame, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture, options: dict, fragment: str
) -> None:
    from orthonav.cli.main import main

    frame, pose = cli_frame
    monkeypatch.setattr(sys, "argv", ["orthonav", *_run_args(frame, pose, **options)])
    with pytest.raises(SystemExit) as info:
        main()
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and fragment in err, err


def test_untrained_trunks_are_the_same_every_run() -> None:
    """Random weights from a fixed seed: two correctors of one backbone compute the same features."""
    import torch

    from orthonav.localize.dense import _network

    config = CorrectionConfig(backbone="mobilenetv2")
    first, _ = _network(config)
    torch.manual_seed(123)  # the caller's random state does not leak into the trunk ...
    second, _ = _network(config)
    image = torch.rand(1, 3, 64, 64)
    assert torch.equal(first(image), second(image))
    state = torch.random.get_rng_state()
    _network(config)
    assert torch.equal(state, torch.random.get_rng_state())  # ... nor the trunk's seed into the caller


def test_corrector_as_a_fix_source_rejects_what_it_cannot_correct(
    naip_raster: GeoRaster, naip2018: GeoRaster, corrector: Corrector
) -> None:
    """``localize`` is the loops' interface: a fix, or a rejection with a reason; never a crash
    for a prior the map cannot serve, but an error for a frame from another camera."""
    pose = pose_at(naip_raster, *CENTRE_PX, yaw=30.0)
    frame = render_frame(naip2018, CAMERA, pose, Photometric(), np.random.default_rng(0))
    fix = corrector.localize(frame, offset_prior(pose))
    assert fix.accepted and fix.method == corrector.method and error_m(fix, pose) < 15.0
    assert corrector.method.startswith("correction:gradient")
    blind = corrector.localize(frame, Prior(alt_agl_m=ALT_M, heading_deg=30.0))
    assert not blind.accepted and "position prior" in blind.reason
    corner_lat, corner_lon = naip_raster.pixel_to_latlon(2.0, 2.0)
    # A prior in the map's corner: searched over the map's ground there, where the frame is not.
    edge = corrector.localize(frame, Prior(float(corner_lat), float(corner_lon), ALT_M, 30.0))
    assert not edge.accepted and edge.reason
    off_map = corrector.localize(frame, Prior(*destination(pose.lat, pose.lon, 0.0, 20_000.0), ALT_M, 30.0))
    assert not off_map.accepted and off_map.reason.startswith("no correction:")
    with pytest.raises(OrthonavError, match="camera"):
        corrector.localize(frame[:100], offset_prior(pose))
