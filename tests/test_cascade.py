"""The cascade fix source on real cross-date NAIP imagery: it fixes frames the keypoint localizer
alone cannot, verification tells a right pose from one 100 m off, the acceptance model rises with
the evidence and ships as its JSON says, and the benchmark runs it side by side."""

from __future__ import annotations

import itertools
import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import CAMERA, NAIP_ALT_M, SHARED_DATA, fixed_with_its_heading, naip_path
from typer.testing import CliRunner

from orthonav.atomic import sha256_file
from orthonav.bench.acceptance import AcceptanceFitConfig
from orthonav.bench.localize import (
    LocalizeBenchConfig,
    Sample,
    _cascade_targets,
    centre_point,
    evaluate_samples,
    render_samples,
)
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, destination, distance_m
from orthonav.localize import (
    CASCADE,
    AcceptanceModel,
    CandidatesConfig,
    Cascade,
    CascadeConfig,
    CoarseConfig,
    CoarseStage,
    Fallback,
    Localizer,
    LocalizerConfig,
    Verifier,
    VerifyConfig,
    learned_parts,
    make_fix_source,
    warm_up,
)
from orthonav.localize.acceptance import (
    FEATURES,
    SHIPPED_ACCEPTANCE,
    SHIPPED_ACCEPTANCE_TRUNK,
    shipped_acceptance_name,
)
from orthonav.localize.cascade import SURE_WITHOUT_TRUNK, cascade_config
from orthonav.localize.dense import trained_trunk
from orthonav.localize.stages import _best_scouted
from orthonav.mapdb import MapPackage, TilingConfig, build_global_index, build_map
from orthonav.models import shipped_model_path
from orthonav.types import Fix, Pose, Prior

# (map year, frames year): the keypoint localizer fixes (almost) none of these frames.
PAIRS = (("20200831", "20180716"), ("20120731", "20200831"))
FRAMES = 6
WRONG_M = 25.0
# Of the first pair's frames without a heading in the prior, at least this many fixed.
FIXED_WITHOUT_HEADING = 4


@pytest.fixture(scope="module")
def maps(tmp_path_factory: pytest.TempPathFactory) -> dict[str, MapPackage]:
    """ORB map packages of the map years, built once."""
    out = tmp_path_factory.mktemp("cascade_maps")
    tiling = TilingConfig(nominal_alt_m=NAIP_ALT_M)
    return {
        year: build_map(naip_path(year), out / year, CAMERA, tiling, progress=False)
        for year in {m for m, _ in PAIRS}
    }


@pytest.fixture(scope="module")
def samples() -> dict[str, list[Sample]]:
    """Frames of the frames years as bench localize renders them (another seed than the fit's)."""
    config = LocalizeBenchConfig(frames=FRAMES, seed=7)
    return {
        year: render_samples(naip_path(year), CAMERA, (NAIP_ALT_M, NAIP_ALT_M), config)
        for year in {f for _, f in PAIRS}
    }


def _pose(sample: Sample, moved_m: float = 0.0) -> Pose:
    """The true pose of a sample, optionally moved ``moved_m`` north-east."""
    t = sample.truth
    lat, lon = destination(t.lat, t.lon, 45.0, moved_m) if moved_m else (t.lat, t.lon)
    clat, clon = centre_point(CAMERA, t)
    return Pose(lat, lon, t.alt_agl_m, t.yaw_deg, t.pitch_deg, t.roll_deg, clat, clon)


@pytest.mark.parametrize(("map_year", "frames_year"), PAIRS)
def test_cascade_fixes_cross_date_frames_the_keypoint_localizer_cannot(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]], map_year: str, frames_year: str
) -> None:
    package = maps[map_year]
    localizer = Localizer(package, CAMERA)
    gained, wrong = 0, []
    with GeoRaster(naip_path(map_year)) as raster:
        cascade = Cascade(package, raster, CAMERA, backend=localizer.backend)
        for s in samples[frames_year]:
            fix = cascade.localize(s.frame, s.prior)
            assert set(fix.timings_ms) >= {"candidates_ms", "coarse_ms", "total_ms"}, fix.timings_ms
            if not fix.accepted:
                continue
            assert 0.0 < fix.quality["p_correct"] <= 1.0 and fix.sigma_m > 0
            assert {"fine_ms", "verify_ms", "accept_ms"} <= set(fix.timings_ms)
            error = float(distance_m(s.truth.lat, s.truth.lon, fix.pose.lat, fix.pose.lon))
            if error > WRONG_M:
                wrong.append(round(error, 1))
            elif not localizer.localize(s.frame, s.prior).accepted:
                gained += 1
    assert not wrong, f"the cascade passed wrong fixes: {wrong} m"
    assert gained >= 2, f"{map_year} <- {frames_year}: only {gained} frames fixed that keypoints miss"


def test_a_correlation_pose_another_place_fits_as_well_is_never_taken(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    """However sure the acceptance model is, a pose without keypoint inliers whose verification
    finds a place beyond its own sigma fitting the frame as well (margin <= 0) is refused, naming
    the rival; a rival within the sigma, or a keypoint pose, is left to the model. Every accepted
    correlation pose stands out or claims its rival's place."""
    map_year, frames_year = PAIRS[0]
    with GeoRaster(naip_path(map_year)) as raster:
        cascade = Cascade(maps[map_year], raster, CAMERA)
        fixes = [cascade.localize(s.frame, s.prior) for s in samples[frames_year]]
        taken = [f for f in fixes if f.accepted and not f.quality["fine_used"]]
        assert taken, "no correlation pose accepted to test the rule on"
        assert all(
            f.quality["verify_margin"] > 0.0 or f.quality["verify_offset_m"] <= f.sigma_m for f in taken
        )
        sigma_m = taken[0].sigma_m
        for margin in (0.0, -0.05):
            beyond = {**taken[0].quality, "verify_margin": margin, "verify_offset_m": 1.5 * sigma_m}
            decided = cascade.accept(replace(taken[0], quality=beyond))
            assert not decided.accepted and "fits the frame as well" in decided.reason, decided.reason
            within = {**beyond, "verify_offset_m": 0.9 * sigma_m}
            assert cascade.accept(replace(taken[0], quality=within)).reason == ""
        pinned = {
            **taken[0].quality,
            "verify_margin": -0.05,
            "verify_offset_m": 3 * sigma_m,
            "fine_used": 1.0,
        }
        assert cascade.accept(replace(taken[0], quality=pinned)).reason == ""


def test_bench_rows_count_the_poses_a_stricter_decision_rejected(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]], tmp_path: Path
) -> None:
    """``placed_centre_within_10m`` is what a perfect decision on the poses found would fix: a
    cascade whose model is sure of nothing (the shipped one, its intercept -100) fixes no frame,
    yet its rejected poses of the same frames count as placed, as many as the shipped one fixes."""
    doubting = json.loads(shipped_model_path(SHIPPED_ACCEPTANCE).read_text()) | {"intercept": -100.0}
    (tmp_path / "doubting.json").write_text(json.dumps(doubting))
    map_year, frames_year = PAIRS[0]
    frames = samples[frames_year]
    with GeoRaster(naip_path(map_year)) as raster:
        shipped = Cascade(maps[map_year], raster, CAMERA)
        config = CascadeConfig(acceptance_path=str(tmp_path / "doubting.json"))
        strict = Cascade(maps[map_year], raster, CAMERA, config)
        rows = [evaluate_samples(source, raster.gsd_m, frames, "prior") for source in (shipped, strict)]
    assert rows[1]["fix_rate"] == 0.0 and rows[1]["centre_within_10m"] == 0.0, rows[1]
    assert rows[0]["centre_within_10m"] >= 0.5, rows[0]
    assert rows[1]["placed_centre_within_10m"] >= rows[0]["centre_within_10m"], rows
    assert rows[0]["placed_centre_within_10m"] >= rows[0]["centre_within_10m"]


def test_verification_scores_the_right_pose_high_and_one_100m_off_low(
    samples: dict[str, list[Sample]],
) -> None:
    map_year, frames_year = PAIRS[0]
    with GeoRaster(naip_path(map_year)) as raster:
        verifier = Verifier(raster, CAMERA)
        checks = [
            (verifier.verify(s.frame, _pose(s)), verifier.verify(s.frame, _pose(s, 100.0)))
            for s in samples[frames_year]
        ]
    for right, off in checks:
        assert right.valid > 0.9 and off.score < 0.1 and off.score < right.score, (right, off)
        # 100 m off, a better place lies in the neighbourhood searched (40 m) or none stands out.
        assert off.margin < 0.0, off
        # The gradients' orientation agrees the same way.
        assert off.orientation_score < right.orientation_score and off.orientation_margin < 0.0, (right, off)
    assert np.median([right.orientation_margin for right, _ in checks]) > 0.0, checks
    # Across dates some ground changed beyond recognition; most frames still agree clearly.
    assert np.median([right.score for right, _ in checks]) > 0.25, checks
    assert np.mean([right.offset_px <= 1.0 for right, _ in checks]) >= 0.75, checks


def test_the_frames_blocks_find_their_place_at_the_right_pose_and_not_20m_off(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    """Each block of the frame, slid alone over the map rendered at the pose, finds its own best
    place at a right pose, across dates; 20 m off (4 map pixels, inside the neighbourhood) the
    blocks each prefer the right place instead. Off the map no block counts: 0."""
    for map_year, frames_year in PAIRS:
        with GeoRaster(naip_path(map_year)) as raster:
            verifier = Verifier(raster, CAMERA)
            for sample in samples[frames_year]:
                right, off = (verifier.verify(sample.frame, _pose(sample, m)) for m in (0.0, 20.0))
                assert right.blocks_at_pose >= 0.6 and off.blocks_at_pose <= 0.2, (right, off)
            far = verifier.verify(sample.frame, _pose(sample, 20_000.0))
            assert far.blocks_at_pose == 0.0
            assert verifier.verify(sample.frame, _pose(sample), blocks=False).blocks_at_pose == 0.0
            # A cascade measures them where a model that may decide weighs them: after the
            # orientation correlation; not after the gradient one, nor on maps finer than the
            # models that weigh them were fitted on; always when asked (records to fit on).
            orientation = cascade_config("orientation")
            oriented = Cascade(maps[map_year], raster, CAMERA, orientation)
            assert oriented.checks_blocks and oriented.checks_trunk  # the models with the trunk
            assert not Cascade(maps[map_year], raster, CAMERA).checks_blocks
            fine = replace(orientation, trunk_min_map_gsd_m=10.0)
            assert not Cascade(maps[map_year], raster, CAMERA, fine).checks_blocks
            asked = replace(fine, blocks_check=True)
            assert Cascade(maps[map_year], raster, CAMERA, asked).checks_blocks
    with pytest.raises(OrthonavError, match="verify: expected blocks >= 0"):
        VerifyConfig(blocks=-1)


def test_the_trunks_agreement_tells_the_right_pose_from_one_60m_off(
    samples: dict[str, list[Sample]],
) -> None:
    """Across dates the trained trunk's features agree best at the right pose: it stands out of
    its neighbourhood there, and 60 m off a better place lies next to it; off the map, no score."""
    map_year, frames_year = PAIRS[0]
    trunk = trained_trunk()
    with GeoRaster(naip_path(map_year)) as raster:
        verifier = Verifier(raster, CAMERA)
        checks = [
            tuple(verifier.trunk_agreement(s.frame, _pose(s, moved), trunk) for moved in (0.0, 60.0))
            for s in samples[frames_year]
        ]
        first = samples[frames_year][0]
        assert verifier.trunk_agreement(first.frame, _pose(first, 20_000.0), trunk) == {}
    for right, off in checks:
        assert -1.0 <= off["trunk_score"] < right["trunk_score"] <= 1.0, (right, off)
        assert off["trunk_margin"] < right["trunk_margin"], (right, off)
    assert np.median([right["trunk_margin"] for right, _ in checks]) > 0.05, checks
    assert np.median([off["trunk_margin"] for _, off in checks]) < 0.0, checks


def test_a_model_that_weighs_the_trunk_gets_its_agreement_measured(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    """Where the trunk loads, the shipped model that weighs its agreement decides and the
    cascade measures it, except where the model without it is already sure (it decides those);
    asked to, it always measures; turned off, the model without it decides and no trunk is loaded
    (no time spent); turning the check off under a model that uses it is refused rather than
    decided on weak evidence."""
    map_year, frames_year = PAIRS[0]
    sample = samples[frames_year][0]
    with GeoRaster(naip_path(map_year)) as raster:
        weighed = Cascade(maps[map_year], raster, CAMERA)
        fixes = [weighed.localize(s.frame, s.prior) for s in samples[frames_year]]
        assert weighed.acceptance.to_dict() == AcceptanceModel.load(backend="orb", trunk=True).to_dict()
        for fix in (f for f in fixes if f.pose is not None):
            q = fix.quality
            if SURE_WITHOUT_TRUNK in q:
                assert q["p_correct"] == q[SURE_WITHOUT_TRUNK] >= 0.99 and fix.accepted, q
                assert "trunk_score" not in q and "trunk_ms" not in fix.timings_ms
            else:
                assert {"trunk_score", "trunk_margin"} <= set(q) and fix.timings_ms["trunk_ms"] > 0.0, q
        always = Cascade(maps[map_year], raster, CAMERA, CascadeConfig(trunk_check=True))
        fix = always.localize(sample.frame, sample.prior)
        assert fix.pose is not None and {"trunk_score", "trunk_margin"} <= set(fix.quality), fix.quality
        assert SURE_WITHOUT_TRUNK not in fix.quality and fix.timings_ms["trunk_ms"] > 0.0
        # Turned off, or a map finer than those the models were fitted on (NAIP's 5 m here).
        for config in (CascadeConfig(trunk_check=False), CascadeConfig(trunk_min_map_gsd_m=10.0)):
            plain = Cascade(maps[map_year], raster, CAMERA, config)
            fix = plain.localize(sample.frame, sample.prior)
            assert not plain.acceptance.uses_trunk
            assert "trunk_score" not in fix.quality and "trunk_ms" not in fix.timings_ms
            assert "trunk" not in plain.__dict__, "the trunk was loaded for a model that does not use it"
        trunk_model = shipped_model_path(SHIPPED_ACCEPTANCE_TRUNK)
        off = CascadeConfig(acceptance_path=str(trunk_model), trunk_check=False)
        with pytest.raises(OrthonavError, match="trunk_check is off"):
            Cascade(maps[map_year], raster, CAMERA, off).localize(sample.frame, sample.prior)
    with pytest.raises(OrthonavError, match="sure_without_trunk: expected a probability in"):
        CascadeConfig(sure_without_trunk=0.0)
    for bad in (-1.0, float("nan")):
        with pytest.raises(OrthonavError, match="trunk_min_map_gsd_m: expected metres >= 0"):
            CascadeConfig(trunk_min_map_gsd_m=bad)


def test_acceptance_probability_rises_with_the_evidence() -> None:
    model = AcceptanceModel.load()
    weak = {
        "coarse_peak_ratio": 1.3,
        "coarse_peak_score": 0.2,
        "coarse_match_score": 0.15,
        "verify_score": 0.08,
        "verify_margin": -0.1,
        "verify_offset_px": 6.0,
        "prior_offset_sigma": 2.5,
        "fine_pose": 0.0,
        "fine_used": 0.0,
    }
    stronger = [
        {"verify_score": 0.3},
        {"verify_score": 0.3, "verify_margin": 0.1, "verify_offset_px": 0.0},
        {"verify_score": 0.3, "verify_margin": 0.1, "verify_offset_px": 0.0, "prior_offset_sigma": 0.5},
    ]
    strongest = {
        **stronger[-1],
        "coarse_peak_ratio": 4.0,
        "coarse_peak_score": 0.5,
        "coarse_match_score": 0.5,
        "verify_score": 0.45,
    }
    keypoints = {"fine_used": 1.0, "fine_inliers": 80.0, "fine_inlier_ratio": 0.4, "fine_rmse_px": 1.0}
    stronger += [strongest, {**strongest, **keypoints}]
    p = [model.probability(weak)] + [model.probability({**weak, **more}) for more in stronger]
    assert all(b > a for a, b in itertools.pairwise(p)), p
    assert p[0] < model.threshold < p[-1], (p, model.threshold)


def test_a_checks_margin_counts_relative_to_its_score() -> None:
    """A right pose of a hazy year scores low and stands out little; its margin as a share of its
    score is what tells it from a near miss that matches as well and stands out less. Bounded to
    [-1, 1]; a score near 0 (or none measured) does not blow the share up."""
    relative = FEATURES["trunk_relative_margin"]
    hazy_right = {"trunk_score": 0.40, "trunk_margin": 0.12}
    near_miss = {"trunk_score": 0.45, "trunk_margin": 0.05}
    assert relative(hazy_right) == pytest.approx(0.3) and relative(near_miss) == pytest.approx(1 / 9)
    assert relative({"trunk_score": 0.001, "trunk_margin": 0.2}) == 1.0
    assert relative({"trunk_score": 0.01, "trunk_margin": -0.3}) == -1.0
    assert relative({}) == -1.0  # not measured: the weak end, as every absent check
    orientation = FEATURES["verify_orientation_relative_margin"]
    assert orientation({"verify_orientation_score": 0.2, "verify_orientation_margin": 0.05}) == pytest.approx(
        0.25
    )
    # The shipped models that weigh them: those with the trunk (ALIKED's after the orientation
    # correlation all three; the others without the trunk's, which passed more false fixes).
    aliked = AcceptanceModel.load(backend="aliked", trunk=True, coarse_backbone="orientation")
    assert {"trunk_relative_margin", "verify_relative_margin"} <= set(aliked.features)
    for backend, backbone in (("orb", "orientation"), ("orb", "gradient"), ("aliked", "gradient")):
        model = AcceptanceModel.load(backend=backend, trunk=True, coarse_backbone=backbone)
        assert "verify_orientation_relative_margin" in model.features, (backend, backbone)
        assert "trunk_relative_margin" not in model.features, (backend, backbone)
    # The frame's blocks at the pose: weighed after the orientation correlation, where the right
    # poses of the hazy year are.
    for backend in ("orb", "aliked"):
        model = AcceptanceModel.load(backend=backend, trunk=True, coarse_backbone="orientation")
        assert "verify_blocks_at_pose" in model.features, backend
        hazy = {"verify_score": 0.3, "trunk_score": 0.3}
        assert model.probability({**hazy, "verify_blocks_at_pose": 1.0}) > model.probability(hazy)


SHIPPED_MODELS = [
    (None, False, "gradient"),
    ("orb", False, "gradient"),
    ("sift", False, "gradient"),
    ("aliked", False, "gradient"),
    ("orb", True, "gradient"),
    ("aliked", True, "gradient"),
    ("orb", True, "trained"),
    ("aliked", True, "trained"),
    ("orb", False, "orientation"),
    ("orb", True, "orientation"),
    ("aliked", False, "orientation"),
    ("aliked", True, "orientation"),
    ("disk", True, "orientation"),
]


@pytest.mark.parametrize(("backend", "trunk", "backbone"), SHIPPED_MODELS)
def test_shipped_acceptance_model_loads_and_matches_its_json(
    backend: str | None, trunk: bool, backbone: str
) -> None:
    """Each shipped model (ORB's, the default; ALIKED's own, without and with the trunk's
    agreement; with it, after each coarse correlation) loads as its JSON says, fitted on its
    backend's and correlation's evidence on one half of the area and scored on the other; one
    that weighs the trunk names the trunk that measured it."""
    path = shipped_model_path(shipped_acceptance_name(backend, trunk, backbone))
    data = json.loads(path.read_text())
    model = AcceptanceModel.load(backend=backend, trunk=trunk, coarse_backbone=backbone)
    assert model.to_dict() == data
    assert data["data"]["keypoint_backend"] == ("aliked" if backend == "aliked" else "orb")
    # Fitted on its own correlation's evidence, but for ORB after the trained one (it did not decide better).
    own = backbone == "orientation" or (backbone == "trained" and backend == "aliked")
    assert data["config"].get("coarse_backbone", "gradient") == (backbone if own else "gradient")
    assert set(model.features) <= set(FEATURES)
    assert model.uses_trunk == trunk
    if trunk:
        described = data["data"]["trunk"]
        assert described["sha256"] == sha256_file(shipped_model_path(described["model"]))
    assert 0.5 <= model.threshold < 1.0
    scores = data["scores"]
    assert set(scores) == {"west", "east"}, "fitted on one half of the area, scored on the other"
    for half in scores.values():
        cross = half["cross-date"]
        assert cross["frames"] > 100 and cross["false_25m"] < 0.005 and cross["fixed"] > 0.3, half
    assert data["data"]["pairs"] >= 2 and path.stat().st_size < 20_000


def test_acceptance_model_json_errors_are_clear(tmp_path: Path) -> None:
    data = AcceptanceModel.load().to_dict()
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({**data, "features": ["nope", *data["features"][1:]]}))
    with pytest.raises(OrthonavError, match="unknown features"):
        AcceptanceModel.load(bad)
    bad.write_text("{")
    with pytest.raises(OrthonavError, match=r"not valid JSON \(acceptance model expected"):
        AcceptanceModel.load(bad)


def test_a_filters_narrow_prior_is_searched_wide_enough_for_a_rival_peak(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    """A navigation filter's prior (30 m, within 20 m of the truth) makes a window barely wider
    than the frame. Searched that narrow, the correlation had no room for a rival peak, its
    ratio saturated at 1000 and the acceptance model, fitted on 200 m priors, took fixes 40-100 m
    off for certain; the region is now at least 1.5 footprints wide, as in the fit."""
    map_year, frames_year = PAIRS[0]
    rng = np.random.default_rng(5)
    with GeoRaster(naip_path(map_year)) as raster:
        cascade = Cascade(maps[map_year], raster, CAMERA)
        for s in samples[frames_year]:
            near = destination(s.truth.lat, s.truth.lon, rng.uniform(0.0, 360.0), 20.0)
            narrow = replace(s.prior, lat=float(near[0]), lon=float(near[1]), sigma_m=30.0)
            window = cascade.candidates.windows(s.frame, narrow)[0]
            assert cascade.coarse.search_factor(window) >= cascade.coarse.config.min_search_factor
            fix = cascade.localize(s.frame, narrow)
            assert fix.quality.get("coarse_peak_ratio", 0.0) < 1000.0, fix.quality
            if fix.accepted:
                assert distance_m(s.truth.lat, s.truth.lon, fix.pose.lat, fix.pose.lon) <= WRONG_M


def test_cascade_rejects_what_it_cannot_search(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    map_year, frames_year = PAIRS[0]
    s = samples[frames_year][0]
    with GeoRaster(naip_path(map_year)) as raster:
        cascade = Cascade(maps[map_year], raster, CAMERA)
        no_altitude = cascade.localize(s.frame, replace(s.prior, alt_agl_m=None))
        assert not no_altitude.accepted and "altitude" in no_altitude.reason
        with pytest.raises(OrthonavError, match="640x480"):
            cascade.localize(s.frame[:100], s.prior)
        far = Prior(*destination(s.prior.lat, s.prior.lon, 90.0, 20_000.0), s.prior.alt_agl_m, 0.0)
        off_map = cascade.localize(s.frame, far)
        assert not off_map.accepted and off_map.reason
        assert json.dumps(off_map.to_dict())


def test_trial_headings_are_evenly_spaced_and_only_where_the_prior_has_no_heading() -> None:
    config = CandidatesConfig(heading_trials=8)
    known = Prior(40.0, -100.0, 1000.0, 33.0)
    assert config.trial_headings(known) == [known]
    trials = config.trial_headings(replace(known, heading_deg=None))
    assert [t.heading_deg for t in trials] == [45.0 * k for k in range(8)]
    assert all(t.heading_sigma_deg == 22.5 and (t.lat, t.lon) == (40.0, -100.0) for t in trials)
    with pytest.raises(OrthonavError, match="heading_trials"):
        CandidatesConfig(heading_trials=0)
    with pytest.raises(OrthonavError, match="lost_trial_regions"):
        CandidatesConfig(lost_trial_regions=0)
    with pytest.raises(OrthonavError, match="index_candidates >= 1"):
        CandidatesConfig(index_candidates=0)
    for scout in ({"scout_px": 224}, {"scout_px": 16}, {"trial_shortlist": 0}, {"region_shortlist": 0}):
        with pytest.raises(
            OrthonavError, match=r"scout_px in 32..223 \(or None\) and trial_shortlist, region_shortlist"
        ):
            CoarseConfig(**scout)


def test_a_prior_without_a_heading_is_searched_at_trial_headings(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    """A compass that failed (or a photo with no heading): the prior's window is searched at
    evenly spaced headings, the best placement again at the heading it found; across dates the
    frames are fixed with the heading found to a few degrees, or rejected, never 25 m off."""
    map_year, frames_year = PAIRS[0]
    fixed = 0
    with GeoRaster(naip_path(map_year)) as raster:
        cascade = Cascade(maps[map_year], raster, CAMERA)
        trials = cascade.candidates.config.heading_trials
        for s in samples[frames_year]:
            no_heading = replace(s.prior, heading_deg=None)
            windows = cascade.candidates.windows(s.frame, no_heading)
            headings = sorted(w.prior.heading_deg for w in windows)
            assert headings == [k * 360.0 / trials for k in range(trials)]
            assert all(w.heading_trial and "heading trial" in w.source for w in windows)
            fix = cascade.localize(s.frame, no_heading)
            assert fix.quality["windows"] == trials
            fixed += fixed_with_its_heading(fix, s.truth, WRONG_M)
    assert fixed >= FIXED_WITHOUT_HEADING, f"only {fixed} of {FRAMES} frames without a heading fixed"


@pytest.mark.parametrize("frames_year", ["20200831", "20180716"], ids=["same-date", "cross-date"])
def test_lost_on_a_map_without_an_index_keypoints_over_every_tile_give_the_window(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]], frames_year: str
) -> None:
    """No position and no global index: the window is the keypoint localizer's fix over every
    tile (what the keypoint fix source alone does when lost), checked by the later stages; the
    same date it is found, across dates rarely, and never more than 25 m off."""
    map_year = "20200831"
    fixed = 0
    with GeoRaster(naip_path(map_year)) as raster:
        cascade = Cascade(maps[map_year], raster, CAMERA)
        for s in samples[frames_year][:3]:
            lost = replace(s.blind, heading_deg=s.prior.heading_deg)
            fix = cascade.localize(s.frame, lost)
            if fix.accepted:
                fixed += 1
                assert fix.quality["windows"] == 1.0
                assert distance_m(s.truth.lat, s.truth.lon, fix.pose.lat, fix.pose.lon) <= WRONG_M
            else:
                assert "no global index" in fix.reason or fix.pose is not None, fix.reason
    assert fixed == 3 or frames_year != map_year, f"same date, only {fixed} of 3 lost frames fixed"


def test_lost_frames_search_the_global_index(samples: dict[str, list[Sample]], tmp_path: Path) -> None:
    map_year, frames_year = PAIRS[0]
    tiling = TilingConfig(nominal_alt_m=NAIP_ALT_M)
    package = build_map(naip_path(map_year), tmp_path / "map", CAMERA, tiling, progress=False)
    package = build_global_index(package, 16, 0, "vlad")
    with GeoRaster(naip_path(map_year)) as raster:
        cascade = Cascade(package, raster, CAMERA)
        for s in samples[frames_year][:3]:
            lost = replace(s.blind, heading_deg=s.prior.heading_deg)
            fix = cascade.localize(s.frame, lost)
            assert fix.quality["windows"] == cascade.candidates.config.index_candidates, fix.reason
            if fix.accepted:
                assert distance_m(s.truth.lat, s.truth.lon, fix.pose.lat, fix.pose.lon) <= WRONG_M


def test_drone_scale_map_wide_window_is_split_and_keypoints_give_the_pose(tmp_path: Path) -> None:
    """At 50-150 m over a 0.25 m map, a 200 m prior is many footprints wide: the correlation
    searches it as several regions on the map (scouted, the best correlated at full size), the
    keypoints search it all, and the decision takes the better verified pose."""
    ortho = SHARED_DATA / "highres" / "nl_aerial_25cm.tif"
    if not ortho.is_file():
        pytest.skip(f"drone-scale orthophoto not available: {ortho} is missing")
    config = LocalizeBenchConfig(frames=4, seed=2)
    frames = render_samples(ortho, CAMERA, (50.0, 150.0), config)
    package = build_map(ortho, tmp_path / "map", CAMERA, TilingConfig(nominal_alt_m=87.0), progress=False)
    with GeoRaster(ortho) as raster:
        cascade = Cascade(package, raster, CAMERA)
        window = cascade.candidates.windows(frames[0].frame, frames[0].prior)[0]
        regions = cascade.coarse.regions(window)
        assert window.scout_regions and 1 < len(regions) <= cascade.coarse.config.max_regions
        assert all(raster.contains_latlon(r.lat, r.lon) for r in regions)
        # Each window's regions are scouted and the 2 best correlated at full size (all of them
        # where no scout placed the frame); the placement is the one every region's full-size
        # correlation gives, and the evidence counts the window's regions.
        shortlist = cascade.coarse.config.region_shortlist
        unscouted = CoarseStage(
            raster, CAMERA, CoarseConfig(region_shortlist=cascade.coarse.config.max_regions)
        )
        kept_counts = []
        for s in frames:
            window = cascade.candidates.windows(s.frame, s.prior)[0]
            regions = cascade.coarse.regions(window)
            kept = cascade.coarse.shortlist_regions(s.frame, regions, cascade.coarse.search_factor(window))
            assert len(regions) > shortlist and (len(kept) == shortlist or kept == regions)
            assert all(region in regions for region in kept)
            kept_counts.append(len(kept))
            scouted, every = cascade.coarse.localize(s.frame, window), unscouted.localize(s.frame, window)
            assert scouted.quality["regions"] == every.quality["regions"] == len(regions)
            assert distance_m(scouted.pose.lat, scouted.pose.lon, every.pose.lat, every.pose.lon) < 0.5
        assert kept_counts.count(shortlist) >= 3, kept_counts
        fixes = [(s, cascade.localize(s.frame, s.prior)) for s in frames]
    errors = [distance_m(s.truth.lat, s.truth.lon, f.pose.lat, f.pose.lon) for s, f in fixes if f.accepted]
    assert len(errors) >= 3 and max(errors) < 2.0, [(f.reason, f.quality.get("p_correct")) for _, f in fixes]


def test_scouts_keep_the_peaks_that_stand_out_most_else_the_first_given() -> None:
    """Scouted regions (or trials) are kept by their peaks; where no scout placed the frame the
    first given are kept (a window's regions come nearest its centre first), not the last."""
    pose = Pose(40.0, -100.0, 1000.0, 0.0, 0.0, 0.0, 40.0, -100.0)

    def placed(ratio: float) -> Fix:
        return Fix(True, pose=pose, quality={"peak_ratio": ratio})

    scouted, unplaced = ["a", "b", "c", "d"], Fix(False, "no peak")
    assert _best_scouted(scouted, [unplaced, placed(2.0), unplaced, placed(3.0)], 2) == ["d", "b"]
    assert _best_scouted(scouted, [placed(2.0), unplaced, placed(2.0), unplaced], 3) == ["a", "c", "b"]
    assert _best_scouted(scouted, [unplaced] * 4, 2) == ["a", "b"]


def test_bench_localize_runs_the_cascade_side_by_side(tmp_path: Path) -> None:
    data = tmp_path / "naip2"
    data.mkdir()
    for year in ("20180716", "20200831"):
        source = naip_path(year)
        (data / source.name).symlink_to(source)
    out = tmp_path / "bench.json"
    args = ["bench", "localize", "--data", str(data), "--no-highres", "--frames", "2"]
    args += ["--speed-sizes", "", "--fix-sources", "cascade,keypoints", "--out", str(out)]
    args += ["--priors", "prior,no heading,no prior"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "orb cascade: cross-date / prior" in result.output
    assert "ms per frame by stage" in result.output
    written = json.loads(out.read_text())
    rows = written["rows"]
    cascade = [r for r in rows if r["method"] == "cascade"]
    assert (tmp_path / "bench_pairs.png").stat().st_size > 10_000  # a matrix of the pairs per method
    # The targets of what ran: the ORB keypoint path's and the cascade's, each checked.
    targets = written["summary"]["targets"]
    assert "orb same-date median time <= 50 ms" in targets
    assert "orb cascade without a prior within 25 m >= 70 % across dates" in targets
    pairs = [r for r in cascade if (r["condition"], r["prior"]) == ("cross-date", "prior")]
    every_pair = "orb cascade frame centre within 10 m >= 90 % on every cross-date pair"
    assert targets[every_pair] == all(r["centre_within_10m"] >= 0.9 for r in pairs)
    assert f"target {every_pair}:" in result.output
    # Same-date with and without a heading, cross-date also without any prior: 2 + 2 + 2 x 3.
    assert len(cascade) == len(rows) // 2 == 10
    for row in cascade:
        assert row["false_25m_rate"] == 0.0, row
        assert {"within_5m", "centre_within_10m", "false_fix_rate"} <= set(row)
        assert row["placed_centre_within_10m"] >= row["centre_within_10m"], row
        if row["prior"] == "prior":
            assert {"coarse_ms", "fine_ms", "verify_ms"} <= set(row["stage_ms"]), row["stage_ms"]
    same = [r for r in cascade if r["condition"] == "same-date" and r["prior"] == "prior"]
    assert all(r["fix_rate"] == 1.0 and r["centre_within_10m"] == 1.0 for r in same), same
    no_heading = [r for r in cascade if r["condition"] == "same-date" and r["prior"] == "no heading"]
    assert len(no_heading) == 2 and sum(r["fix_rate"] for r in no_heading) >= 1.5, no_heading
    assert "orb cascade: same-date / no heading" in written["summary"]
    # Each accepted cascade fix's P(right) beside its error; pooled, set against the rate right.
    assert all(len(r["p_correct"]) == len(r["errors_m"]) for r in cascade if r["errors_m"])
    assert all("p_correct" not in r for r in rows if r["method"] == "keypoints")
    same_pooled = written["summary"]["orb cascade: same-date / prior"]
    accepted = sum(len(r["errors_m"]) for r in same)
    assert same_pooled["calibration"]["fixes"] == accepted
    observed = same_pooled["calibration"]["bins"][0]["observed"]
    assert observed == 1.0  # every same-date fix within 25 m (checked above)
    calibrated = "orb cascade P(right) within 5 points of the observed rate per decile, across dates"
    assert (
        targets[calibrated]
        == written["summary"]["orb cascade: cross-date / prior"]["calibration"]["within_tolerance"]
    )
    assert out.with_name("bench_reliability_orb_cascade.png").is_file()


def test_bench_localize_lists_only_the_targets_of_the_conditions_that_ran() -> None:
    """A run of lost frames alone reports the lost target, not the prior's as 'not met'."""
    lost_only = {"orb cascade: cross-date / no prior": {"within_25m": 0.29}}
    assert _cascade_targets("orb", lost_only, []) == {
        "orb cascade without a prior within 25 m >= 70 % across dates": False
    }


def test_the_fine_stage_budget_follows_the_matcher(maps: dict[str, MapPackage], samples: dict) -> None:
    """ORB's fine stage matches four tiles with every frame keypoint; a keypoint density keeps
    the strongest for the view's size (and still fixes a same-date frame); a density of zero or
    less is refused by name."""
    package = maps["20200831"]
    with GeoRaster(package.source_path) as raster:
        fine = Cascade(package, raster, CAMERA).fine
        assert fine.max_tiles == 4 and fine.localizer.config.frame_keypoint_density is None
        assert not fine.localizer.config.guided  # ORB's own matcher
    sample = samples["20200831"][0]
    everything = Localizer(package, CAMERA).localize(sample.frame, sample.prior)
    view = package.frame_view(CAMERA, sample.frame, sample.prior)
    budget = round(2.0 * np.count_nonzero(view.mask) / 1000.0)
    assert everything.quality["keypoints"] > budget > 30
    dense = Localizer(package, CAMERA, LocalizerConfig(frame_keypoint_density=2.0))
    fix = dense.localize(sample.frame, sample.prior)
    assert fix.accepted, fix.reason
    assert fix.quality["keypoints"] == budget
    with pytest.raises(OrthonavError, match=r"frame_keypoint_density 0\.0: expected None or keypoints"):
        LocalizerConfig(frame_keypoint_density=0.0)


def test_guided_matching_fixes_near_the_prior_and_never_lends_it_a_pose(
    maps: dict[str, MapPackage], samples: dict
) -> None:
    """Guided by a prior good to 15 m and 3 deg, ORB fixes a same-date frame within 10 m of its
    centre; the same prior moved 300 m (beyond the search radius) gets no fix: chance pairs near
    the wrong place do not agree on its pose."""
    package = maps["20200831"]
    localizer = Localizer(package, CAMERA, LocalizerConfig(guided=True))
    for sample in samples["20200831"][:2]:
        t = sample.truth
        prior = replace(sample.prior, lat=t.lat, lon=t.lon, heading_deg=t.yaw_deg, sigma_m=15.0)
        prior = replace(prior, heading_sigma_deg=3.0)
        fix = localizer.localize(sample.frame, prior)
        assert fix.accepted, fix.reason
        assert distance_m(fix.pose.centre_lat, fix.pose.centre_lon, *sample.centre) < 10.0
        lat, lon = destination(t.lat, t.lon, 45.0, 300.0)
        moved = localizer.localize(sample.frame, replace(prior, lat=lat, lon=lon))
        assert not moved.accepted, moved.reason
    with pytest.raises(OrthonavError, match="guided_ratio in"):
        LocalizerConfig(guided_ratio=1.5)


def test_the_coarse_correlation_is_selectable_by_name(maps: dict[str, MapPackage]) -> None:
    """The cascade's coarse stage runs seed 003's CNN correlation (the shipped trunk) when asked;
    by default the gradient one, then the orientation one where it rejects the frame (two
    cascades, one keypoint backend); a name that is no backbone is refused before any map is read."""
    package = maps["20200831"]
    with GeoRaster(package.source_path) as raster:
        default = make_fix_source(CASCADE, package, CAMERA, raster)
        trained = make_fix_source(CASCADE, package, CAMERA, raster, coarse_backbone="trained")
    assert isinstance(default, Fallback) and default.names == ["cascade-gradient", "cascade-orientation"]
    first, second = default.sources
    assert [s.coarse.corrector.config.backbone for s in (first, second)] == ["gradient", "orientation"]
    assert first.fine.localizer.backend is second.fine.localizer.backend
    assert trained.coarse.corrector.config.backbone == "trained"
    # The heading trials' and scouts' correctors share the trunk loaded once, and the
    # verification's check compares with that same network.
    coarse = trained.coarse
    assert trained.trunk is coarse.corrector.network
    for other, size_px in (
        (coarse.trial_corrector, 224),
        (coarse.scout_corrector, coarse.config.scout_px),
    ):
        assert other.network is coarse.corrector.network is not None
        assert (other.config.size_px, other.config.refine, other.config.backbone) == (
            size_px,
            "none",
            "trained",
        )
    assert coarse.corrector.config.refine == "ecc"
    with pytest.raises(
        OrthonavError, match="coarse backbone 'sobel': expected one of gradient, orientation, trained"
    ):
        LocalizeBenchConfig(coarse_backbone="sobel")


def test_after_the_trained_correlation_its_own_model_decides(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    """The trained correlation's peaks and poses are not the gradient one's: the model with the
    trunk's agreement decides every proposal (ALIKED's fitted on its evidence; ORB's own was no
    better), never the model without the trunk (fitted on the gradient one's, it passed a false
    fix more there). ``bench acceptance`` refuses a correlation it does not have."""
    map_year, frames_year = PAIRS[0]
    with GeoRaster(naip_path(map_year)) as raster:
        trained = make_fix_source(CASCADE, maps[map_year], CAMERA, raster, coarse_backbone="trained")
        fixes = [trained.localize(s.frame, s.prior) for s in samples[frames_year][:6]]
    own = AcceptanceModel.load(backend="orb", trunk=True, coarse_backbone="trained")
    assert trained.acceptance.to_dict() == own.to_dict() and own.uses_trunk
    aliked = AcceptanceModel.load(backend="aliked", trunk=True, coarse_backbone="trained")
    assert aliked.info["config"]["coarse_backbone"] == "trained"
    posed = [fix for fix in fixes if fix.pose is not None]
    assert posed, [fix.reason for fix in fixes]
    for fix in posed:
        assert "trunk_score" in fix.quality and SURE_WITHOUT_TRUNK not in fix.quality, fix.quality
        assert fix.quality["p_correct"] == pytest.approx(own.probability(fix.quality))
    with pytest.raises(
        OrthonavError, match="coarse backbone 'sobel': expected one of gradient, orientation, trained"
    ):
        AcceptanceFitConfig(coarse_backbone="sobel")


def test_after_the_orientation_correlation_its_own_models_decide(
    maps: dict[str, MapPackage], samples: dict[str, list[Sample]]
) -> None:
    """The orientation correlation's cascade decides with the models fitted on its evidence,
    which weigh the verification's orientation check; chained after the gradient one it is asked
    only where that one rejects (a frame it fixes is the gradient cascade's fix)."""
    map_year, frames_year = PAIRS[0]
    with GeoRaster(naip_path(map_year)) as raster:
        chain = make_fix_source(
            CASCADE, maps[map_year], CAMERA, raster, coarse_backbone="gradient>orientation"
        )
        gradient, orientation = chain.sources
        fixes = [orientation.localize(s.frame, s.prior) for s in samples[frames_year][:4]]
        first = chain.localize(samples[frames_year][0].frame, samples[frames_year][0].prior)
    assert chain.names == ["cascade-gradient", "cascade-orientation"]
    assert orientation.coarse.corrector.config.backbone == "orientation"
    assert gradient.coarse.corrector.config.backbone == "gradient"
    own = AcceptanceModel.load(backend="orb", trunk=orientation.checks_trunk, coarse_backbone="orientation")
    assert orientation.acceptance.to_dict() == own.to_dict()
    assert {"verify_orientation_score", "verify_orientation_margin"} <= set(own.features)
    posed = [fix for fix in fixes if fix.pose is not None]
    assert posed, [fix.reason for fix in fixes]
    for fix in posed:
        assert -1.0 <= fix.quality["verify_orientation_score"] <= 1.0
        assert "p_correct" in fix.quality
    assert first.accepted and first.method == gradient.method, first.reason


def test_coarse_correlations_chain_cheapest_first(maps: dict[str, MapPackage]) -> None:
    """``gradient>trained``: a cascade with each coarse correlation, the trained one asked only
    where the gradient one rejects; both share the orthophoto and the keypoint backend, and the
    warm-up runs both so the first rejected frame does not load the trunk."""
    package = maps["20200831"]
    with GeoRaster(package.source_path) as raster:
        chain = make_fix_source(CASCADE, package, CAMERA, raster, coarse_backbone="gradient>trained")
        assert isinstance(chain, Fallback) and chain.names == ["cascade-gradient", "cascade-trained"]
        first, second = chain.sources
        assert [s.coarse.corrector.config.backbone for s in chain.sources] == ["gradient", "trained"]
        assert first.coarse.raster is second.coarse.raster is raster
        assert first.fine.localizer.backend is second.fine.localizer.backend
        asked: list[str] = []
        for name, source in zip(chain.names, chain.sources, strict=True):
            source.localize = _recording(source.localize, asked, name)
        fix = warm_up(chain, raster, CAMERA, NAIP_ALT_M)
        assert fix.accepted, fix.reason
        assert asked == ["cascade-gradient", "cascade-trained"]
        # Map fallbacks (fly --fallback) of such chains: every cascade of each is warmed and said.
        maps_chain = Fallback([chain, chain], ["orb", "orb"])
        warm_up(maps_chain, raster, CAMERA, NAIP_ALT_M)
        assert asked[2:] == ["cascade-gradient", "cascade-trained"] * 2
        assert learned_parts(maps_chain) == learned_parts(chain) != []
    for bad in ("gradient>", "gradient>sobel"):
        with pytest.raises(OrthonavError, match=f"coarse backbone '{bad}': expected"):
            LocalizeBenchConfig(coarse_backbone=bad)


def _recording(localize: Callable, asked: list[str], name: str) -> Callable:
    def recorded(*args: object) -> Fix:
        asked.append(name)
        return localize(*args)

    return recorded
