"""Global re-localization on the real NAIP 2020 map: VLAD tile descriptors searched with faiss."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import CAMERA, naip_path
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, destination, distance_m
from orthonav.localize import Localizer, LocalizerConfig
from orthonav.mapdb import MapPackage, TilingConfig, build_global_index, build_map, cut_corridor
from orthonav.mapdb.globalindex import GLOBAL, GlobalIndex, train_index
from orthonav.types import Prior

pytest.importorskip("faiss", reason="the global index needs faiss (the 'scale' extra)")

ALT_M = 700.0  # 35 tiles on the NAIP quarter-quad: enough to make a search worth it
FRAMES = 12


@pytest.fixture(scope="module")
def indexed_map(tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    out = tmp_path_factory.mktemp("indexed") / "map"
    package = build_map(naip_path("20200831"), out, CAMERA, TilingConfig(nominal_alt_m=ALT_M), progress=False)
    return build_global_index(package, words=32)


@pytest.fixture(scope="module")
def frames(naip_raster: GeoRaster) -> list[tuple[np.ndarray, TruePose]]:
    """Same-date frames at random places and headings, away from the map's edges."""
    rng = np.random.default_rng(5)
    out = []
    for _ in range(FRAMES):
        lat, lon = naip_raster.pixel_to_latlon(
            rng.uniform(0.2, 0.8) * naip_raster.width, rng.uniform(0.2, 0.8) * naip_raster.height
        )
        pose = TruePose(float(lat), float(lon), ALT_M, float(rng.uniform(0, 360)), 0.0, 0.0)
        out.append((render_frame(naip_raster, CAMERA, pose, Photometric(), rng), pose))
    return out


def _blind(pose: TruePose) -> Prior:
    """What a lost vehicle still knows: altitude, compass heading, attitude."""
    return Prior(alt_agl_m=ALT_M, heading_deg=pose.yaw_deg, pitch_deg=0.0, roll_deg=0.0)


def test_the_right_tile_is_among_the_first_five(indexed_map: MapPackage, frames) -> None:
    localizer = Localizer(indexed_map, CAMERA)
    ranks = []
    for frame, pose in frames:
        found, scores = indexed_map.global_index.search(localizer.frame_view(frame, _blind(pose)), 10)
        assert np.all(np.diff(scores) <= 1e-6)  # best first
        under = set(indexed_map.tiles_within(pose.lat, pose.lon, 0.0).tolist())
        ranks.append(next((r for r, tile in enumerate(found) if tile in under), 99))
    print(f"\nrank of the first tile under the drone: {ranks}")
    assert np.mean(np.array(ranks) < 5) >= 0.9


def test_lost_frames_are_fixed_from_the_top_tiles_only(indexed_map: MapPackage, frames) -> None:
    """Without a position prior the localizer matches 10 retrieved tiles, not all 35, and fixes."""
    retrieved, brute = (
        Localizer(indexed_map, CAMERA),
        Localizer(indexed_map, CAMERA, LocalizerConfig(global_candidates=0)),
    )
    fixed = 0
    for frame, pose in frames:
        fix = retrieved.localize(frame, _blind(pose))
        assert fix.quality["tiles"] <= 10
        if fix.accepted:
            assert distance_m(fix.pose.lat, fix.pose.lon, pose.lat, pose.lon) < 25.0
            fixed += 1
    assert fixed >= 0.8 * len(frames)
    frame, pose = frames[0]
    assert brute.localize(frame, _blind(pose)).quality["tiles"] == len(indexed_map)


def test_vlad_descriptors_are_unit_vectors_and_the_index_round_trips(
    indexed_map: MapPackage, tmp_path
) -> None:
    index = indexed_map.global_index
    assert index.tile_vectors.shape == (len(indexed_map), 32 * 256)  # ORB: 256 bits per word
    np.testing.assert_allclose(np.linalg.norm(index.tile_vectors, axis=1), 1.0, atol=1e-5)
    assert not np.any(index.describe(np.zeros((0, 32), np.uint8)))
    index.write(tmp_path / GLOBAL)
    again = GlobalIndex.read(tmp_path / GLOBAL)
    np.testing.assert_array_equal(again.tile_vectors, index.tile_vectors)
    record = json.loads((indexed_map.path / "manifest.json").read_text())["global_index"]
    assert record["words"] == 32 and record["method"] == "vlad"


def test_a_corridor_keeps_its_tiles_index_rows(
    indexed_map: MapPackage, naip_raster: GeoRaster, tmp_path
) -> None:
    lat, lon = naip_raster.center_latlon
    route = [destination(lat, lon, 270.0, 800.0), destination(lat, lon, 90.0, 800.0)]
    corridor = cut_corridor(indexed_map, route, 800.0, tmp_path / "corridor")
    kept = [
        int(np.argmin(np.abs(indexed_map.tiles.corners_latlon[:, 2] - c).sum(1)))
        for c in corridor.tiles.corners_latlon[:, 2]
    ]
    np.testing.assert_array_equal(
        corridor.global_index.tile_vectors, indexed_map.global_index.tile_vectors[kept]
    )


def test_damaged_index_and_bad_training_are_named(indexed_map: MapPackage, tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(indexed_map.path, copy)
    (copy / GLOBAL).write_bytes(b"not an index")
    with pytest.raises(OrthonavError, match="damaged"):
        _ = MapPackage(copy).global_index
    with pytest.raises(OrthonavError, match="too few"):
        train_index(lambda tile: np.zeros((10, 32), np.uint8), np.array([0, 10]), words=32)


def test_cli_adds_an_index(naip_map: MapPackage, tmp_path: Path) -> None:
    copy = tmp_path / "map"
    shutil.copytree(naip_map.path, copy)
    result = CliRunner().invoke(app, ["map", "index", str(copy), "--words", "16"])
    assert result.exit_code == 0, result.output
    assert MapPackage(copy).global_index.words.shape == (16, 256)
