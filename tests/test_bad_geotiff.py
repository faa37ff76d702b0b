"""Every kind of bad orthophoto is refused with an OrthonavError naming the file and the expectation."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from affine import Affine
from helpers_geotiff import UTM14_ORIGIN, textured, write_geotiff

from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster

X0, Y0 = UTM14_ORIGIN


def missing(tmp: Path) -> Path:
    return tmp / "nowhere.tif"


def directory(tmp: Path) -> Path:
    path = tmp / "folder.tif"
    path.mkdir()
    return path


def text_file(tmp: Path) -> Path:
    path = tmp / "notes.tif"
    path.write_text("this is not an image\n" * 20)
    return path


def png_renamed(tmp: Path) -> Path:
    png = tmp / "photo.png"
    cv2.imwrite(str(png), np.moveaxis(textured(64, 64), 0, -1))
    return png.rename(tmp / "photo.tif")


def jpeg_raster(tmp: Path) -> Path:
    path = tmp / "photo.jpg"
    cv2.imwrite(str(path), np.moveaxis(textured(64, 64), 0, -1))
    return path


def no_crs(tmp: Path) -> Path:
    return write_geotiff(tmp / "nocrs.tif", textured(64, 64), crs=None)


def rotated(tmp: Path) -> Path:
    t = Affine.translation(X0, Y0) @ Affine.rotation(15.0) @ Affine.scale(1.0, -1.0)
    return write_geotiff(tmp / "rotated.tif", textured(64, 64), transform=t)


def zero_y_size(tmp: Path) -> Path:
    return write_geotiff(tmp / "zero_y.tif", textured(64, 64), transform=Affine(1, 0, X0, 0, 0, Y0))


def south_up(tmp: Path) -> Path:
    return write_geotiff(tmp / "south_up.tif", textured(64, 64), transform=Affine(1, 0, X0, 0, 1, Y0))


def mirrored(tmp: Path) -> Path:
    return write_geotiff(tmp / "mirrored.tif", textured(64, 64), transform=Affine(-1, 0, X0, 0, -1, Y0))


def wgs84_holding_metres(tmp: Path) -> Path:
    t = Affine(1, 0, 500000.0, 0, -1, 5200000.0)
    return write_geotiff(tmp / "wgs84_metres.tif", textured(64, 64), crs="EPSG:4326", transform=t)


def utm_east_of_zone(tmp: Path) -> Path:
    # 1300 km east of the central meridian of zone 14 (99 W): about 82 W, Lake Huron.
    t = Affine(1, 0, 1_800_000.0, 0, -1, Y0)
    return write_geotiff(tmp / "utm_far_east.tif", textured(64, 64), transform=t)


def utm_north_zone_south_coords(tmp: Path) -> Path:
    # Northings of a northern-hemisphere zone that land at 27 S.
    t = Affine(1, 0, 500000.0, 0, -1, -3_000_000.0)
    return write_geotiff(tmp / "utm_south.tif", textured(64, 64), transform=t)


def all_zero(tmp: Path) -> Path:
    return write_geotiff(tmp / "zeros.tif", np.zeros((3, 64, 64), np.uint8))


def all_nodata(tmp: Path) -> Path:
    return write_geotiff(tmp / "nodata.tif", np.full((3, 64, 64), 255, np.uint8), nodata=255)


def all_nan(tmp: Path) -> Path:
    return write_geotiff(tmp / "nan.tif", np.full((1, 64, 64), np.nan, np.float32), nodata=np.nan)


def constant(tmp: Path) -> Path:
    return write_geotiff(tmp / "flat.tif", np.full((3, 64, 64), 117, np.uint8))


def two_bands(tmp: Path) -> Path:
    return write_geotiff(tmp / "two.tif", textured(64, 64, bands=2))


def tiny(tmp: Path) -> Path:
    return write_geotiff(tmp / "tiny.tif", textured(8, 8))


def wrong_dtype(tmp: Path) -> Path:
    data = textured(64, 64).astype(np.int32) * 1000
    return write_geotiff(tmp / "int32.tif", data)


# (maker, regex the message must match: what was wrong or expected)
CASES: dict[str, tuple[Callable[[Path], Path], str]] = {
    "missing": (missing, r"no such file.*expected a GeoTIFF"),
    "directory": (directory, r"is a directory.*expected a GeoTIFF"),
    "text_file": (text_file, r"not a readable GeoTIFF"),
    "png_renamed": (png_renamed, r"is a PNG raster, expected a GeoTIFF"),
    "jpeg": (jpeg_raster, r"is a JPEG raster, expected a GeoTIFF"),
    "no_crs": (no_crs, r"no coordinate reference system.*expected a georeferenced"),
    "rotated": (rotated, r"rotated or sheared.*expected north-up"),
    "zero_y_size": (zero_y_size, r"degenerate or flipped.*expected positive x size and negative y size"),
    "south_up": (south_up, r"degenerate or flipped.*expected positive x size and negative y size"),
    "mirrored": (mirrored, r"degenerate or flipped.*expected positive x size and negative y size"),
    "wgs84_holding_metres": (wgs84_holding_metres, r"geographic CRS EPSG:4326.*not degrees"),
    "utm_east_of_zone": (utm_east_of_zone, r"outside the area where .*UTM zone 14N is valid"),
    "utm_south": (utm_north_zone_south_coords, r"outside the area where .*UTM zone 14N is valid"),
    "all_zero": (all_zero, r"imagery is empty"),
    "all_nodata": (all_nodata, r"imagery is empty"),
    "all_nan": (all_nan, r"imagery is empty"),
    "constant": (constant, r"single constant value"),
    "two_bands": (two_bands, r"has 2 bands, expected 1 \(gray\), 3 \(RGB\) or 4"),
    "tiny": (tiny, r"only 8x8 px.*expected at least 16x16"),
    "wrong_dtype": (wrong_dtype, r"pixel type int32, expected one of"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_orthophoto_is_refused_clearly(tmp_path: Path, case: str) -> None:
    """A bad map raises exactly OrthonavError whose message names the file and the problem."""
    make, pattern = CASES[case]
    path = make(tmp_path)
    with pytest.raises(Exception) as exc:
        GeoRaster(path)
    assert type(exc.value) is OrthonavError, f"{type(exc.value).__name__}: {exc.value}"
    message = str(exc.value)
    assert str(path) in message
    assert re.search(pattern, message), message


def test_good_synthetic_file_opens(tmp_path: Path) -> None:
    """The same writer with sane settings gives a map that opens: the bad cases fail for their flaw."""
    path = write_geotiff(tmp_path / "good.tif", textured(64, 64))
    with GeoRaster(path) as raster:
        assert (raster.width, raster.height, raster.band_count) == (64, 64, 3)
        assert raster.gsd_m == pytest.approx(1.0, rel=1e-3)


def _tiled(tmp: Path, size: int = 1024) -> Path:
    """An uncompressed GeoTIFF of 256 px blocks (random pixels: every block differs)."""
    import rasterio

    data = np.random.default_rng(0).integers(0, 255, (3, size, size)).astype("uint8")
    path = tmp / "tiled.tif"
    profile = {"driver": "GTiff", "width": size, "height": size, "count": 3, "dtype": "uint8"}
    profile |= {"crs": "EPSG:32614", "transform": Affine(1, 0, 500000, 0, -1, 5200000)}
    with rasterio.open(path, "w", tiled=True, blockxsize=256, blockysize=256, **profile) as ds:
        ds.write(data)
    return path


def test_a_truncated_geotiff_is_refused_in_one_line_and_leaves_nothing(tmp_path: Path) -> None:
    """A file cut short (an interrupted copy): a clear error naming the file, from opening it
    and from a map build, with no partial package left behind."""
    from typer.testing import CliRunner

    from orthonav.cli.main import app

    full = _tiled(tmp_path)
    cut = tmp_path / "cut.tif"
    cut.write_bytes(full.read_bytes()[: int(full.stat().st_size * 0.6)])
    with pytest.raises(OrthonavError, match=r"cut\.tif: .*truncated or damaged"):
        GeoRaster(cut)
    out = tmp_path / "map"
    result = CliRunner().invoke(app, ["map", "build", str(cut), "--out", str(out), "--altitude", "600"])
    assert isinstance(result.exception, OrthonavError) and "truncated or damaged" in str(result.exception)
    assert not out.exists() and not out.with_name("map.partial").exists()


def test_every_block_is_read_once_and_a_bad_block_is_named(tmp_path: Path, monkeypatch) -> None:
    from rasterio.errors import RasterioIOError

    with GeoRaster(_tiled(tmp_path)) as raster:
        seen = []
        raster.check_readable(lambda done, total: seen.append((done, total)))
        assert seen[-1] == (16, 16) and len(seen) == 16
        real_read = raster._ds.read

        def failing(*args, **kwargs):
            window = kwargs.get("window")
            if window is not None and (window.row_off, window.col_off) == (512, 256):
                raise RasterioIOError("TIFFReadEncodedTile() failed")
            return real_read(*args, **kwargs)

        monkeypatch.setattr(raster._ds, "read", failing)
        with pytest.raises(OrthonavError, match=r"block 2,1 \(rows 512\.\.768, columns 256\.\.512\)"):
            raster.check_readable()
