"""Dense correlation re-localizes a lost vehicle across dates through the map's cnn global index.

The map is the west of the 2018 quad (3 km x 3.6 km) with a cnn index; frames come from 2020.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import CAMERA, write_naip_crop

from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize import CorrectionConfig, Corrector
from orthonav.mapdb import MapPackage, TilingConfig, build_global_index, build_map
from orthonav.sim import MissionConfig, run_mission
from orthonav.types import Fix, Prior

pytest.importorskip("faiss", reason="the global index needs faiss (the 'scale' extra)")
pytest.importorskip("torch", reason="the cnn global index needs torch (the 'learned' extra)")

ALT_M = 1000.0
MAP_COLS = 600  # of the quad's 934 columns (5 m/px): the map is its west 3 km
FIXED_WITHIN_M = 25.0


@pytest.fixture(scope="module")
def crop_tifs(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The 2018 map's orthophoto and the whole 2020 quad (the frames' date), as GeoTIFFs."""
    out = tmp_path_factory.mktemp("relocalize")
    map_tif = write_naip_crop("20180716", (0, 0, MAP_COLS, 724), out / "map_2018.tif")
    return map_tif, write_naip_crop("20200831", (0, 0, 934, 724), out / "frames_2020.tif")


@pytest.fixture(scope="module")
def cnn_map(
    crop_tifs: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory, torch_one_thread
) -> MapPackage:
    out = tmp_path_factory.mktemp("relocalize_map") / "map"
    package = build_map(crop_tifs[0], out, CAMERA, TilingConfig(nominal_alt_m=ALT_M), progress=False)
    return build_global_index(package, method="cnn")


def _frame(
    frames: GeoRaster, col: float, row: float, heading: float, seed: int
) -> tuple[np.ndarray, TruePose]:
    rng = np.random.default_rng(seed)
    lat, lon = frames.pixel_to_latlon(col, row)
    pose = TruePose(float(lat), float(lon), ALT_M, heading, 0.0, 0.0)
    return render_frame(frames, CAMERA, pose, Photometric.random(rng, 0.6), rng), pose


def _lost(pose: TruePose) -> Prior:
    """What a lost vehicle knows: altitude, compass heading, attitude; no position."""
    return Prior(alt_agl_m=ALT_M, heading_deg=pose.yaw_deg, pitch_deg=0.0, roll_deg=0.0)


def _error_m(fix: Fix, pose: TruePose) -> float:
    return float(distance_m(fix.pose.lat, fix.pose.lon, pose.lat, pose.lon))


def test_a_lost_frame_of_another_year_is_fixed_through_the_index(
    cnn_map: MapPackage, crop_tifs: tuple[Path, Path]
) -> None:
    places = [(150, 200, 20.0), (420, 250, 135.0), (250, 520, 250.0), (450, 560, 300.0)]
    with GeoRaster(crop_tifs[0]) as ortho, GeoRaster(crop_tifs[1]) as frames:
        plain = Corrector(ortho, CAMERA)
        relocalizing = Corrector(ortho, CAMERA, package=cnn_map)
        errors = []
        for i, (col, row, heading) in enumerate(places):
            frame, pose = _frame(frames, col, row, heading, i)
            rejected = plain.localize(frame, _lost(pose))
            assert not rejected.accepted and "needs a position prior" in rejected.reason
            fix = relocalizing.localize(frame, _lost(pose))
            print(f"\n{i}: {fix.accepted} {fix.reason[:160]} {fix.quality.get('peak_ratio')}")
            if fix.accepted:
                errors.append(_error_m(fix, pose))
                assert fix.method == "correction:gradient-224+index"
                assert 0 <= fix.quality["index_rank"] < CorrectionConfig().index_candidates
    print(f"errors of accepted fixes: {np.round(errors, 1)}")
    assert len(errors) >= 2, "fewer than 2 of 4 lost cross-date frames fixed"
    assert max(errors) <= FIXED_WITHIN_M  # never a wrong fix passed as accepted


def test_without_an_index_the_rejection_says_why(cnn_map: MapPackage, crop_tifs, tmp_path: Path) -> None:
    plain_map = build_map(
        crop_tifs[0], tmp_path / "map", CAMERA, TilingConfig(nominal_alt_m=ALT_M), progress=False
    )
    assert plain_map.global_index is None
    with GeoRaster(crop_tifs[0]) as ortho, GeoRaster(crop_tifs[1]) as frames:
        frame, pose = _frame(frames, 150, 200, 20.0, 0)
        fix = Corrector(ortho, CAMERA, package=plain_map).localize(frame, _lost(pose))
        assert not fix.accepted and fix.pose is None
        assert "needs a position prior" in fix.reason and "global index" in fix.reason
        no_heading = Corrector(ortho, CAMERA, package=cnn_map).localize(frame, Prior(alt_agl_m=ALT_M))
        assert not no_heading.accepted and "altitude and heading" in no_heading.reason


def test_a_frame_over_ground_the_map_lacks_is_rejected(cnn_map: MapPackage, crop_tifs) -> None:
    """The east of the quad, entirely outside the map: the index still returns its best tiles,
    and every one of them must be refused."""
    with GeoRaster(crop_tifs[0]) as ortho, GeoRaster(crop_tifs[1]) as frames:
        corrector = Corrector(ortho, CAMERA, package=cnn_map)
        for i, (row, heading) in enumerate(((200, 0.0), (520, 90.0))):
            frame, pose = _frame(frames, 820, row, heading, 10 + i)
            fix = corrector.localize(frame, _lost(pose))
            print(f"\n{fix.reason[:200]}")
            assert not fix.accepted and fix.reason.startswith("lost: ")
            assert "index candidate" in fix.reason or "ambiguous" in fix.reason


def test_a_lost_correlation_mission_recovers(cnn_map: MapPackage, crop_tifs, tmp_path: Path) -> None:
    """GNSS lost from the start and a start zone 1.1 km wide: the filter's sigma is beyond its
    1 km limit, it is lost from the first frame; correlation around the index's tiles gives the
    fixes that re-initialise it (two that agree)."""
    start = cnn_map.grid.pixel_to_latlon(300, 420)
    target = cnn_map.grid.pixel_to_latlon(300, 100)
    config = MissionConfig(
        *map(float, start), *map(float, target), start_zone_m=1100.0, max_time_s=40.0, seed=3
    )
    with GeoRaster(crop_tifs[0]) as ortho, GeoRaster(crop_tifs[1]) as frames:
        corrector = Corrector(ortho, CAMERA, package=cnn_map)
        run_mission(cnn_map, frames, CAMERA, config, tmp_path, progress=False, fix_source=corrector)
    steps = [json.loads(line) for line in (tmp_path / "steps.jsonl").read_text().splitlines()]
    print([(s["nav_status"], s["accepted"], s["error_m"] and round(s["error_m"])) for s in steps])
    relocalized = [s for s in steps if s["accepted"] and s["fix"]["method"].endswith("+index")]
    assert relocalized, "no fix from the index while the filter was lost"
    assert steps[0]["nav_status"] == "lost" and not steps[0]["accepted"]
    assert all(s["error_m"] <= FIXED_WITHIN_M for s in relocalized)
    recovered = [s for s in steps if s["nav_status"] == "fixed"]
    assert recovered and recovered[0]["step"] <= relocalized[0]["step"] + 2
    assert max(s["nav_error_m"] for s in recovered) < 50.0


def test_bench_fix_sources_are_checked() -> None:
    from orthonav.bench.relocalize import RelocalizeBenchConfig
    from orthonav.errors import OrthonavError

    assert RelocalizeBenchConfig(fix_sources=("keypoints", "correlation")).fix_sources[1] == "correlation"
    with pytest.raises(OrthonavError, match="expected some of keypoints, correlation"):
        RelocalizeBenchConfig(fix_sources=("sift",))
