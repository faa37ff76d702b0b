"""Mosaics of the real NAIP years and the re-localization and map-build benchmarks on them, cut down."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import rasterio
from conftest import NAIP_YEARS, naip_path
from rasterio.windows import Window
from typer.testing import CliRunner

from orthonav.bench.mapbuild import MapBuildBenchConfig, run_mapbuild_benchmark
from orthonav.bench.mosaic import mosaic_layout, write_mosaic
from orthonav.bench.relocalize import RelocalizeBenchConfig, run_relocalize_benchmark
from orthonav.cli.main import app
from orthonav.errors import OrthonavError

pytest.importorskip("faiss", reason="the global index needs faiss (the 'scale' extra)")


@pytest.fixture(scope="module")
def years() -> list[Path]:
    return [naip_path(year) for year in NAIP_YEARS]


def test_mosaic_blocks_are_the_sources_quarters_mirrored_and_redated(years, tmp_path: Path) -> None:
    mosaic = mosaic_layout(years, 24)
    assert len(set(mosaic.blocks)) == 24
    assert sum(b.mirror for b in mosaic.blocks) == 4  # 5 dates x 4 quarters come first
    out = write_mosaic(mosaic, tmp_path / "m.tif")
    redated = write_mosaic(mosaic, tmp_path / "s.tif", every_block_from=years[-1])
    bw, bh = mosaic.block_px
    with rasterio.open(out) as m, rasterio.open(redated) as s, rasterio.open(years[0]) as first:
        assert m.crs == first.crs and m.width == mosaic.per_row * bw
        for i in (0, 7, 23):
            block = mosaic.blocks[i]
            col, row = mosaic.origin_px(i)
            qr, qc = divmod(block.quarter, 2)
            for image, date in ((m, block.date), (s, len(years) - 1)):
                with rasterio.open(years[date]) as src:
                    expected = src.read(window=Window(qc * bw, qr * bh, bw, bh))
                got = image.read(window=Window(col, row, bw, bh))
                np.testing.assert_array_equal(got, expected[:, :, ::-1] if block.mirror else expected)
    with pytest.raises(OrthonavError, match="1 to 40 distinct blocks"):
        mosaic_layout(years, 41)
    repeated = mosaic_layout(years, 45, repeat=True)
    assert repeated.blocks[40:] == mosaic.blocks[:5] and len(set(repeated.blocks)) == 40


def test_benchmark_rows_compare_the_index_with_every_tile(years, tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    config = RelocalizeBenchConfig(blocks=(2,), frames=4)
    result = run_relocalize_benchmark(years, out, config, progress=False)
    rows = result["rows"]
    assert [r["condition"] for r in rows] == ["same-date", "cross-date"]
    same = rows[0]
    assert same["km2"] == pytest.approx(8.4, abs=0.2) and same["tiles"] > 4
    assert same["recall@1"] <= same["recall@5"] <= same["recall@10"] and same["recall@10"] >= 0.75
    assert same["fixed index"] >= 0.75 and same["ms index"] > 0 and same["ms all tiles"] > 0
    assert json.loads(out.read_text())["config"]["frames"] == 4
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_index_only_run_and_too_few_dates(years, tmp_path: Path) -> None:
    """``all_tiles=False`` leaves the slow every-tile columns out; one date cannot give cross-date frames."""
    config = RelocalizeBenchConfig(blocks=(1,), frames=2, all_tiles=False)
    rows = run_relocalize_benchmark(years, tmp_path / "b.json", config, progress=False)["rows"]
    assert all("ms index" in r and "ms all tiles" not in r for r in rows)
    with pytest.raises(OrthonavError, match="at least two dates"):
        run_relocalize_benchmark(years[:1], tmp_path / "c.json", config, progress=False)


def test_index_methods_side_by_side(years, tmp_path: Path) -> None:
    """Each index method gets its rows on the same frames, with recall of any copy of the ground."""
    pytest.importorskip("torch", reason="the cnn index needs torch (the 'learned' extra)")
    config = RelocalizeBenchConfig(blocks=(1,), frames=2, all_tiles=False, indexes=("vlad", "cnn"))
    rows = run_relocalize_benchmark(years, tmp_path / "b.json", config, progress=False)["rows"]
    assert [(r["index"], r["condition"]) for r in rows] == [
        ("vlad", "same-date"),
        ("vlad", "cross-date"),
        ("cnn", "same-date"),
        ("cnn", "cross-date"),
    ]
    assert all(r["recall@10"] <= r["recall@10 any copy"] for r in rows)
    with pytest.raises(OrthonavError, match="expected some of vlad, cnn"):
        RelocalizeBenchConfig(indexes=("bow",))


def test_the_cascade_relocalizes_from_the_index(years, tmp_path: Path) -> None:
    """The cascade as a fix source beside the keypoints, on the same lost frames: its columns are
    there, same-date frames are fixed and no fix is wrong."""
    config = RelocalizeBenchConfig(
        blocks=(1,), frames=3, all_tiles=False, fix_sources=("keypoints", "cascade")
    )
    rows = run_relocalize_benchmark(years, tmp_path / "b.json", config, progress=False)["rows"]
    same = rows[0]
    assert same["condition"] == "same-date" and same["ms cascade"] > 0
    assert same["fixed cascade"] >= 2 / 3 and all(r["wrong cascade"] == 0.0 for r in rows)
    with pytest.raises(OrthonavError, match="expected some of keypoints, correlation, cascade"):
        RelocalizeBenchConfig(fix_sources=("orb",))


def test_cli_names_a_missing_data_folder(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["bench", "relocalize", "--data", str(tmp_path / "nope")])
    assert isinstance(result.exception, OrthonavError) and "nope" in str(result.exception)


def test_mapbuild_benchmark_measures_each_build_on_its_own(years, tmp_path: Path) -> None:
    out = tmp_path / "mapbuild.json"
    result = run_mapbuild_benchmark(years, out, MapBuildBenchConfig(blocks=(2,), workers=(0, 2)))
    single, dask = result["rows"]
    assert (single["workers"], dask["workers"]) == ("single", 2)
    assert single["tiles"] == dask["tiles"] > 0 and single["km2"] == pytest.approx(8.4, abs=0.2)
    for row in (single, dask):
        # Seconds are rounded to 10 ms: that much uncertainty, relative to a build of a second or less.
        rounding = 0.005 / row["seconds"]
        assert row["km2_per_min"] == pytest.approx(row["km2"] / row["seconds"] * 60, rel=0.01 + rounding)
        assert row["km2_per_min_at_0.5m"] == pytest.approx(row["km2_per_min"] / 100, rel=0.02)
        assert 50 < row["peak_mb"] < 4000
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
