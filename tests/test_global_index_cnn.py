"""The cnn global index: tiles and north-up frames described by the shipped retrieval network."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import CAMERA, naip_path
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, destination
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage, TilingConfig, build_global_index, build_map, cut_corridor
from orthonav.mapdb.globalindex import GLOBAL, GlobalIndex
from orthonav.types import Prior

pytest.importorskip("faiss", reason="the global index needs faiss (the 'scale' extra)")
pytest.importorskip("torch", reason="the cnn global index needs torch (the 'learned' extra)")

ALT_M = 700.0
FRAMES = 10


@pytest.fixture(scope="module")
def cnn_map(tmp_path_factory: pytest.TempPathFactory, torch_one_thread) -> MapPackage:
    """A map of 2018 with a cnn index; the frames come from 2020."""
    out = tmp_path_factory.mktemp("cnn") / "map"
    package = build_map(naip_path("20180716"), out, CAMERA, TilingConfig(nominal_alt_m=ALT_M), progress=False)
    return build_global_index(package, method="cnn")


def _ranks(package: MapPackage, year: str) -> tuple[list[int], float]:
    """Rank of the first tile under the drone for frames of ``year``, and that rank's mean for a
    random order of the tiles."""
    rng = np.random.default_rng(3)
    localizer = Localizer(package, CAMERA)
    ranks, chance = [], []
    with GeoRaster(naip_path(year)) as raster:
        for _ in range(FRAMES):
            lat, lon = raster.pixel_to_latlon(
                rng.uniform(0.2, 0.8) * raster.width, rng.uniform(0.2, 0.8) * raster.height
            )
            pose = TruePose(float(lat), float(lon), ALT_M, float(rng.uniform(0, 360)), 0.0, 0.0)
            frame = render_frame(raster, CAMERA, pose, Photometric(), rng)
            prior = Prior(alt_agl_m=ALT_M, heading_deg=pose.yaw_deg, pitch_deg=0.0, roll_deg=0.0)
            found, _ = package.global_index.search(localizer.frame_view(frame, prior), len(package))
            under = set(package.tiles_within(pose.lat, pose.lon, 0.0).tolist())
            ranks.append(next(r for r, tile in enumerate(found) if tile in under))
            chance.append((len(package) - len(under)) / (len(under) + 1))
    return ranks, float(np.mean(chance))


def test_a_frame_of_another_year_retrieves_its_tile_better_than_chance(cnn_map: MapPackage) -> None:
    ranks, chance = _ranks(cnn_map, "20200831")
    print(f"\ncross-date ranks {ranks}, random order: {chance:.1f} on average ({len(cnn_map)} tiles)")
    assert np.median(ranks) <= 0.5 * chance


def test_cnn_index_round_trip_and_checksum(cnn_map: MapPackage, tmp_path: Path) -> None:
    index = cnn_map.global_index
    record = json.loads((cnn_map.path / "manifest.json").read_text())["global_index"]
    assert record["method"] == "cnn" and record["model"] == "retrieval_naip.pt"
    assert len(record["model_sha256"]) == 64 and record["model_sha256"] == index.model_sha256
    np.testing.assert_allclose(np.linalg.norm(index.tile_vectors, axis=1), 1.0, atol=1e-4)
    index.write(tmp_path / GLOBAL)
    again = GlobalIndex.read(tmp_path / GLOBAL)
    assert (again.method, again.model, again.model_sha256) == ("cnn", index.model, index.model_sha256)
    np.testing.assert_array_equal(again.tile_vectors, index.tile_vectors)
    copy = tmp_path / "copy"
    shutil.copytree(cnn_map.path, copy)
    np.savez(copy / GLOBAL, words=index.words, tile_vectors=index.tile_vectors[::-1])
    with pytest.raises(OrthonavError, match="damaged"):
        _ = MapPackage(copy).global_index


def test_a_corridor_keeps_the_cnn_rows(cnn_map: MapPackage, tmp_path: Path) -> None:
    lat, lon = cnn_map.grid.center_latlon
    route = [destination(lat, lon, 270.0, 800.0), destination(lat, lon, 90.0, 800.0)]
    corridor = cut_corridor(cnn_map, route, 800.0, tmp_path / "corridor")
    kept = [
        int(np.argmin(np.abs(cnn_map.tiles.corners_latlon[:, 2] - c).sum(1)))
        for c in corridor.tiles.corners_latlon[:, 2]
    ]
    assert corridor.global_index.method == "cnn" and 0 < len(kept) < len(cnn_map)
    np.testing.assert_array_equal(corridor.global_index.tile_vectors, cnn_map.global_index.tile_vectors[kept])


def test_a_missing_learned_extra_is_named(cnn_map: MapPackage, monkeypatch, tmp_path: Path) -> None:
    """Without torch: building a cnn index needs it; searching one takes the shipped model's ONNX
    graph; a model of one's own without an exported graph names what would make one."""
    import orthonav.models
    from orthonav.atomic import sha256_file

    monkeypatch.setenv("ORTHONAV_CACHE_DIR", str(tmp_path / "empty-cache"))  # no ONNX export to fall back on

    monkeypatch.delitem(sys.modules, "orthonav.models.retrieval", raising=False)
    monkeypatch.delattr(orthonav.models, "retrieval", raising=False)
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch now raises ImportError
    with pytest.raises(OrthonavError, match=r"orthonav\[learned\]"):
        build_global_index(cnn_map, method="cnn")
    index = GlobalIndex.read(cnn_map.path / GLOBAL)
    assert index.network.path.name == "retrieval_naip.onnx"  # shipped beside the model
    own = tmp_path / "own.pt"
    shutil.copy(orthonav.models.shipped_model_path(index.model), own)
    mine = GlobalIndex(index.words, index.tile_vectors, "cnn", str(own), sha256_file(own))
    with pytest.raises(OrthonavError, match=r"orthonav\[learned\]"):
        _ = mine.network


def test_wrong_or_changed_model_files_are_refused(cnn_map: MapPackage, tmp_path: Path) -> None:
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a model")
    with pytest.raises(OrthonavError, match="not a readable model file"):
        build_global_index(cnn_map, method="cnn", model=str(junk))
    from orthonav.models import shipped_model_path

    with pytest.raises(OrthonavError, match="not an orthonav retrieval model"):
        build_global_index(cnn_map, method="cnn", model=str(shipped_model_path()))
    index = cnn_map.global_index
    changed = GlobalIndex(index.words, index.tile_vectors, "cnn", index.model, "0" * 64)
    with pytest.raises(OrthonavError, match="sha256 differs"):
        _ = changed.network
    with pytest.raises(OrthonavError, match="expected one of vlad, cnn"):
        build_global_index(cnn_map, method="netvlad")


def test_cli_builds_a_cnn_index(naip_map: MapPackage, tmp_path: Path) -> None:
    copy = tmp_path / "map"
    shutil.copytree(naip_map.path, copy)
    result = CliRunner().invoke(app, ["map", "index", str(copy), "--method", "cnn"])
    assert result.exit_code == 0, result.output
    index = MapPackage(copy).global_index
    assert index.method == "cnn" and index.tile_vectors.shape == (len(naip_map), 128)
