"""A map built from a folder of orthophotos in different CRSs and resolutions (real NAIP 2020)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.shutil
from conftest import CAMERA, NAIP_ALT_M, naip_path, write_naip_crop
from pyproj import CRS
from rasterio.vrt import WarpedVRT
from rasterio.warp import calculate_default_transform
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.geo.mosaic import build_vrt, mosaic_sources
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.types import Prior

MERCATOR = CRS.from_epsg(3857)


def reproject_file(src_path: Path, out: Path, crs: CRS, res: float) -> Path:
    """The test's own reprojection (rasterio, whole file), independent of the code under test."""
    with rasterio.open(src_path) as src:
        transform, width, height = calculate_default_transform(
            src.crs, crs, src.width, src.height, *src.bounds, resolution=res
        )
        with WarpedVRT(src, crs=crs, transform=transform, width=width, height=height, nodata=0) as warped:
            profile = {
                **src.profile,
                "crs": crs,
                "transform": transform,
                "width": width,
                "height": height,
                "nodata": 0,
            }
            with rasterio.open(out, "w", **profile) as dst:
                dst.write(warped.read())
    return out


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """West half in UTM 14N at 5 m, east half (overlapping by 100 px) in Web Mercator at 9 m
    (Mercator metres: about 6 m on the ground at 47 N, coarser than the west half)."""
    root = tmp_path_factory.mktemp("mosaic")
    (root / "tiles").mkdir()
    write_naip_crop("20200831", (0, 0, 520, 724), root / "tiles" / "a_west.tif")
    east = write_naip_crop("20200831", (420, 0, 514, 724), root / "east_utm.tif")
    reproject_file(east, root / "tiles" / "b_east_mercator.tif", MERCATOR, 9.0)
    return root / "tiles"


@pytest.fixture(scope="module")
def mosaic_map(folder: Path, tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    out = tmp_path_factory.mktemp("mosaic_map") / "map"
    result = CliRunner().invoke(
        app, ["map", "build", str(folder), "--out", str(out), "--altitude", str(NAIP_ALT_M)]
    )
    assert result.exit_code == 0, result.output
    return MapPackage(out)


def test_vrt_puts_both_halves_on_one_utm_grid(folder: Path, tmp_path: Path) -> None:
    vrt = build_vrt(mosaic_sources(folder), tmp_path / "m.vrt")
    copies = sorted(tmp_path.glob("m.*.tif"))
    assert [p.name for p in copies] == ["m.001.tif"]  # only the Mercator half was reprojected
    with GeoRaster(vrt) as mosaic, GeoRaster(naip_path("20200831")) as original:
        assert mosaic.crs == original.crs and mosaic.gsd_m == pytest.approx(original.gsd_m, rel=1e-3)
        for col_share in (0.2, 0.8):  # one point in each half, compared with the original
            lat, lon = original.pixel_to_latlon(col_share * original.width, 0.5 * original.height)
            windows = []
            for raster in (mosaic, original):
                col, row = raster.latlon_to_pixel(lat, lon)
                windows.append(raster.read_rgb(_window(col, row)).astype(float))
            assert np.abs(windows[0] - windows[1]).mean() < 12.0, col_share


def _window(col: float, row: float):
    from orthonav.geo import PixelWindow

    return PixelWindow(float(col) - 40, float(row) - 40, 80, 80)


def test_frames_over_either_half_are_fixed_on_the_mosaic_map(mosaic_map: MapPackage) -> None:
    assert mosaic_map.source_path.suffix == ".vrt" and mosaic_map.source_path.is_file()
    localizer = Localizer(mosaic_map, CAMERA)
    with GeoRaster(naip_path("20200831")) as original:
        for col_share in (0.25, 0.75):
            lat, lon = original.pixel_to_latlon(col_share * original.width, 0.5 * original.height)
            truth = TruePose(float(lat), float(lon), NAIP_ALT_M, 30.0, 0.0, 0.0)
            frame = render_frame(original, CAMERA, truth, Photometric(), np.random.default_rng(1))
            fix = localizer.localize(
                frame, Prior(truth.lat, truth.lon, NAIP_ALT_M, 30.0, 0.0, 0.0, sigma_m=100.0)
            )
            assert fix.accepted, fix.reason
            assert distance_m(fix.pose.lat, fix.pose.lon, truth.lat, truth.lon) < 15.0


def test_bad_folders_and_options_are_named(folder: Path, tmp_path: Path) -> None:
    with pytest.raises(OrthonavError, match="no GeoTIFF"):
        mosaic_sources(tmp_path)
    with pytest.raises(OrthonavError, match="projected CRS"):
        build_vrt(mosaic_sources(folder), tmp_path / "geo.vrt", crs="EPSG:4326")
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    west = folder / "a_west.tif"
    (mixed / "a.tif").symlink_to(west)
    with rasterio.open(west) as src:
        profile = {**src.profile, "count": 1}
        with rasterio.open(mixed / "b.tif", "w", **profile) as dst:
            dst.write(src.read(1), 1)
    with pytest.raises(OrthonavError, match=r"b\.tif: 1 bands"):
        build_vrt(mosaic_sources(mixed), tmp_path / "mixed.vrt")
    result = CliRunner().invoke(
        app, ["map", "build", str(west), "--out", str(tmp_path / "x"), "--crs", "EPSG:32614"]
    )
    assert isinstance(result.exception, OrthonavError) and "folder" in str(result.exception)


def test_mosaic_crs_resolution_is_the_finest_ground_resolution(folder: Path, tmp_path: Path) -> None:
    """On a Web Mercator grid, the 5 m UTM half sets the resolution: 5 ground metres, i.e.
    5 / cos(lat) Mercator units, not 5 Mercator units (which would oversample 2.1 times)."""
    vrt = build_vrt(mosaic_sources(folder), tmp_path / "mercator.vrt", crs="EPSG:3857")
    with GeoRaster(vrt) as mosaic, GeoRaster(folder / "a_west.tif") as west:
        assert mosaic.crs == MERCATOR
        assert mosaic.gsd_m == pytest.approx(west.gsd_m, rel=0.01)
        lat, _ = mosaic.center_latlon
        assert abs(mosaic.transform.a) == pytest.approx(west.gsd_m / np.cos(np.radians(lat)), rel=0.01)


@pytest.fixture(scope="module")
def gap_map(tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    """Two NAIP strips 2.2 km apart (442 px at 5 m) with no imagery between them."""
    root = tmp_path_factory.mktemp("gap")
    (root / "tiles").mkdir()
    write_naip_crop("20200831", (0, 0, 250, 724), root / "tiles" / "a.tif")
    write_naip_crop("20200831", (692, 0, 242, 724), root / "tiles" / "b.tif")
    out = root / "map"
    result = CliRunner().invoke(
        app, ["map", "build", str(root / "tiles"), "--out", str(out), "--altitude", str(NAIP_ALT_M)]
    )
    assert result.exit_code == 0, result.output
    return MapPackage(out)


def test_a_gap_between_files_has_no_features_and_gives_no_fix(gap_map: MapPackage) -> None:
    """Tiles inside the gap carry no features; a frame over the gap is rejected with a reason,
    frames over the imagery on either side are fixed."""
    with GeoRaster(naip_path("20200831")) as original:
        gap_px = [gap_map.grid.latlon_to_pixel(*original.pixel_to_latlon(c, 362))[0] for c in (250, 692)]
        box = gap_map.tiles.box_px
        inside = (box[:, 0] >= gap_px[0] - 0.5) & (box[:, 2] <= gap_px[1] + 0.5)
        assert inside.any(), f"no tile lies wholly in the gap: {box[:, [0, 2]].tolist()}"
        assert all(len(gap_map.tile_features(int(i))) == 0 for i in np.flatnonzero(inside))
        localizer = Localizer(gap_map, CAMERA)
        verdicts = {}
        for name, col in (("west", 125), ("gap", 471), ("east", 813)):
            lat, lon = original.pixel_to_latlon(col, 362)
            truth = TruePose(float(lat), float(lon), NAIP_ALT_M, 0.0, 0.0, 0.0)
            frame = render_frame(original, CAMERA, truth, Photometric(), np.random.default_rng(2))
            fix = localizer.localize(
                frame, Prior(truth.lat, truth.lon, NAIP_ALT_M, 0.0, 0.0, 0.0, sigma_m=100.0)
            )
            verdicts[name] = fix
    assert verdicts["west"].accepted and verdicts["east"].accepted, verdicts
    for name in ("west", "east"):
        pose = verdicts[name].pose
        lat, lon = original.pixel_to_latlon({"west": 125, "east": 813}[name], 362)
        assert distance_m(pose.lat, pose.lon, float(lat), float(lon)) < 15.0
    assert not verdicts["gap"].accepted and verdicts["gap"].reason


def test_cloud_optimized_geotiff_builds_the_same_map(tmp_path: Path) -> None:
    """A COG (tiled, with overviews, GDAL's COG driver) is read window by window like any
    GeoTIFF: the same feature chunks, byte for byte, as the plain GeoTIFF it was made from."""
    plain = write_naip_crop("20200831", (100, 100, 400, 400), tmp_path / "plain.tif")
    cog = tmp_path / "cog.tif"
    rasterio.shutil.copy(plain, cog, driver="COG", blocksize=256, overview_resampling="average")
    with rasterio.open(cog) as ds:
        assert ds.profile["tiled"] and ds.block_shapes[0] == (256, 256) and ds.overviews(1)
    maps = [
        build_map(
            path,
            tmp_path / f"{path.stem}.map",
            CAMERA,
            TilingConfig(nominal_alt_m=NAIP_ALT_M),
            progress=False,
        )
        for path in (plain, cog)
    ]
    chunks = [sorted((m.path / "features").iterdir()) for m in maps]
    assert len(chunks[0]) == len(chunks[1]) > 0 and maps[0].keypoint_count > 500
    assert all(a.read_bytes() == b.read_bytes() for a, b in zip(*chunks, strict=True))
