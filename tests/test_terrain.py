"""Synthetic demo terrain: determinism, georeferencing, texture for ORB, water, atomic writes."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import rasterio
from pyproj import CRS, Geod, Transformer
from rasterio.enums import Compression

from orthonav import atomic
from orthonav.errors import OrthonavError
from orthonav.sim.terrain import TerrainConfig, render_terrain, write_terrain_geotiff

SMALL = TerrainConfig(size_px=512)


@pytest.fixture(scope="module")
def small_image() -> np.ndarray:
    return render_terrain(SMALL)


def test_render_shape_and_dtype(small_image: np.ndarray) -> None:
    assert small_image.shape == (512, 512, 3)
    assert small_image.dtype == np.uint8


def test_same_seed_renders_identical_image(small_image: np.ndarray) -> None:
    assert np.array_equal(render_terrain(SMALL), small_image)


def test_different_seed_renders_different_image(small_image: np.ndarray) -> None:
    other = render_terrain(TerrainConfig(size_px=512, seed=SMALL.seed + 1))
    assert np.mean(other != small_image) > 0.5


@pytest.mark.parametrize(
    "bad",
    [{"size_px": 16}, {"gsd_m": 0.0}, {"gsd_m": float("nan")}, {"center_lat": 86.0}],
)
def test_invalid_config_is_rejected(bad: dict) -> None:
    with pytest.raises(OrthonavError):
        TerrainConfig(**bad)


@pytest.mark.parametrize(
    ("lat", "lon", "zone", "gsd"),
    [
        (50.45, 30.52, "36N", 1.0),  # the default centre, near Kyiv
        (-33.92, 18.42, "34S", 0.5),  # southern hemisphere, finer GSD
        (48.0, 30.0, None, 2.0),  # exactly on the 35/36 zone boundary: either is fine
    ],
)
def test_geotiff_round_trip(tmp_path: Path, lat: float, lon: float, zone: str, gsd: float) -> None:
    config = TerrainConfig(size_px=256, gsd_m=gsd, center_lat=lat, center_lon=lon, seed=3)
    path = write_terrain_geotiff(tmp_path / "map.tif", config)
    assert path == tmp_path / "map.tif"

    with rasterio.open(path) as ds:
        crs = CRS.from_user_input(ds.crs)
        transform = ds.transform
        assert (ds.width, ds.height, ds.count) == (256, 256, 3)
        assert ds.compression == Compression.deflate
        assert ds.block_shapes == [(256, 256)] * 3
        pixels = np.moveaxis(ds.read(), 0, -1)

    assert crs.utm_zone is not None and crs.datum.name.startswith("World Geodetic System 1984")
    if zone is not None:
        assert crs.utm_zone == zone
    assert (transform.b, transform.d) == (0.0, 0.0)
    assert transform.a == pytest.approx(gsd) and transform.e == pytest.approx(-gsd)
    assert np.array_equal(pixels, render_terrain(config))

    half = config.size_px / 2
    east, north = transform.c + transform.a * half, transform.f + transform.e * half
    lon_c, lat_c = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(east, north)
    _, _, error_m = Geod(ellps="WGS84").inv(lon, lat, lon_c, lat_c)
    assert error_m < 1.0


@pytest.mark.parametrize("seed", [7, 11, 2024])
def test_orb_finds_keypoints_almost_everywhere(seed: int) -> None:
    """A camera frame can land anywhere on the map, so nearly every 64 m block needs corners.

    Each block is searched on its own (a mask over the full image, so ORB's border margin
    applies only at the image edges): what matters is local texture, not a global ranking.
    With flat-coloured fields only bushes, edges and houses give corners and this fails.
    """
    gray = cv2.cvtColor(render_terrain(TerrainConfig(size_px=512, seed=seed)), cv2.COLOR_RGB2GRAY)
    orb = cv2.ORB_create(500)
    step = gray.shape[0] // 8
    textured = 0
    for row in range(8):
        for col in range(8):
            mask = np.zeros_like(gray)
            mask[row * step : (row + 1) * step, col * step : (col + 1) * step] = 255
            textured += len(orb.detect(gray, mask)) >= 20
    assert textured >= 0.85 * 64


@pytest.mark.parametrize("seed", [7, 11, 2024])
def test_water_exists_but_is_limited(seed: int) -> None:
    image = render_terrain(TerrainConfig(size_px=512, seed=seed)).astype(int)
    red, green, blue = image[..., 0], image[..., 1], image[..., 2]
    water = (blue > green) & (blue > red + 15)
    assert 0.005 < water.mean() < 0.30


def test_atomic_write_leaves_no_temp_files(tmp_path: Path) -> None:
    target = tmp_path / "map.tif"
    write_terrain_geotiff(target, SMALL)
    write_terrain_geotiff(target, SMALL)  # overwriting an existing map
    assert [p.name for p in tmp_path.iterdir()] == ["map.tif"]


def test_failed_write_keeps_old_map(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "map.tif"
    target.write_bytes(b"previous map")

    def fail(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(atomic.os, "replace", fail)
    with pytest.raises(OSError, match="disk full"):
        write_terrain_geotiff(target, TerrainConfig(size_px=128))
    assert [p.name for p in tmp_path.iterdir()] == ["map.tif"]
    assert target.read_bytes() == b"previous map"
