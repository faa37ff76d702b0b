"""Terrain heights in map packages: a DSM/DEM attached, resampled, filled, checked and read back.

Real data: a 60 x 60 m crop of Seneca's orthophoto (a road, trees and a house) with Seneca's
DSM, read in place. A synthetic map with a planar DSM checks the pixel convention exactly
(bilinear interpolation reproduces a plane) without the real data.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import rasterio
import rasterio.warp
from affine import Affine
from helpers_geotiff import shared_file
from rasterio.crs import CRS as RioCRS
from rasterio.enums import Resampling
from rasterio.windows import from_bounds
from typer.testing import CliRunner

from orthonav.camera import Camera
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.mapdb import MapPackage, TilingConfig, attach_terrain, build_map, cut_corridor
from orthonav.mapdb.terrain import bilinear
from orthonav.sim.terrain import TerrainConfig, write_terrain_geotiff

SENECA = "real/seneca"
# 60 x 60 m in UTM 17N south-east of the crossroads: the diagonal road, trees and a house.
CROP = (306247.5, 4545215.0, 306307.5, 4545275.0)
MARGIN_M = 10.0  # the DSM crops used below reach this far beyond the map
SMALL_CAM = Camera.from_hfov(160, 120, 60.0)
SMALL_TILING = TilingConfig(nominal_alt_m=200.0, scale_coef=1.0, overlap=0.5)
PLANE = (0.02, -0.03, 250.0)  # height = a * x + b * y + c over the synthetic map (x, y from its corner)
runner = CliRunner()


# --- helpers ------------------------------------------------------------------------------------


def crop_raster(src_path: Path, bounds: tuple[float, float, float, float], out: Path, **profile) -> Path:
    """The pixels of ``src_path`` within ``bounds`` (its CRS) as a GeoTIFF of their own."""
    with rasterio.open(src_path) as src:
        window = from_bounds(*bounds, transform=src.transform).round_offsets().round_lengths()
        data = src.read(window=window)
        meta = src.profile.copy()
    meta.update(
        width=data.shape[2],
        height=data.shape[1],
        transform=rasterio.windows.transform(window, meta["transform"]),
    )
    meta.update(driver="GTiff", compress="deflate", **profile)
    meta.pop("photometric", None)
    with rasterio.open(out, "w", **meta) as dst:
        dst.write(data)
    return out


def write_dsm(
    out: Path, heights: np.ndarray, crs: object, transform: Affine, nodata: float | None = -9999.0
) -> Path:
    profile = {"driver": "GTiff", "width": heights.shape[1], "height": heights.shape[0], "count": 1}
    profile.update(dtype="float32", crs=crs, transform=transform, nodata=nodata)
    with rasterio.open(out, "w", **profile) as dst:
        dst.write(heights.astype(np.float32)[None])
    return out


def read_dsm(path: Path) -> tuple[np.ndarray, dict]:
    with rasterio.open(path) as ds:
        return ds.read(1), ds.profile.copy()


def reproject_dsm(path: Path, crs: str, out: Path) -> Path:
    """``path`` warped to ``crs`` (bilinear, nodata kept), as a DSM of that CRS would come."""
    with rasterio.open(path) as src:
        transform, width, height = rasterio.warp.calculate_default_transform(
            src.crs, crs, src.width, src.height, *src.bounds
        )
        heights = np.full((height, width), -9999.0, np.float32)
        rasterio.warp.reproject(
            rasterio.band(src, 1),
            heights,
            dst_transform=transform,
            dst_crs=crs,
            dst_nodata=-9999.0,
            resampling=Resampling.bilinear,
        )
    return write_dsm(out, heights, RioCRS.from_user_input(crs), transform)


def copy_map(package: MapPackage, tmp_path: Path) -> MapPackage:
    """A private copy of a module's map, for tests that attach terrain to it."""
    return MapPackage(shutil.copytree(package.path, tmp_path / package.path.name))


def smooth_points(package: MapPackage, dsm: Path, count: int = 60) -> np.ndarray:
    """Work-grid pixels at DSM cell centres on smooth ground (3 x 3 cells within 0.1 m), where
    any correct interpolation agrees with the cell's value."""
    with rasterio.open(dsm) as ds:
        xs, ys = package.grid.pixel_to_crs([0, package.grid.width], [package.grid.height, 0])
        window = from_bounds(xs[0], ys[0], xs[1], ys[1], transform=ds.transform).round_offsets()
        window = window.round_lengths()
        heights = ds.read(1, window=window)
        transform = ds.window_transform(window)
    rows, cols = np.mgrid[2 : heights.shape[0] - 2, 2 : heights.shape[1] - 2]
    stack = np.stack([heights[rows + dr, cols + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
    smooth = np.ptp(stack, axis=0) < 0.1
    rng = np.random.default_rng(1)
    pick = rng.choice(np.flatnonzero(smooth), count, replace=False)
    x, y = transform @ (cols.ravel()[pick] + 0.5, rows.ravel()[pick] + 0.5)
    return np.column_stack(package.grid.crs_to_pixel(x, y))


def dsm_heights(dsm: Path, package: MapPackage, map_px: np.ndarray) -> np.ndarray:
    """What the DSM itself says at work-grid pixels (its cell there, read by rasterio)."""
    x, y = package.grid.pixel_to_crs(map_px[:, 0], map_px[:, 1])
    with rasterio.open(dsm) as ds:
        return np.array([v[0] for v in ds.sample(zip(x, y, strict=True))], float)


def expect_error(call, *fragments: str) -> str:
    with pytest.raises(OrthonavError) as info:
        call()
    for fragment in fragments:
        assert fragment in str(info.value), (fragment, str(info.value))
    return str(info.value)


# --- real data: Seneca --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def seneca_dsm() -> Path:
    return shared_file(f"{SENECA}/dsm.tif")


@pytest.fixture(scope="module")
def seneca_map(tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    """A map of the 60 x 60 m crop for the 1600 x 1200 camera at 65 m (one tile, ~1 s)."""
    ortho, camera = shared_file(f"{SENECA}/ortho.tif"), shared_file(f"{SENECA}/camera.json")
    folder = tmp_path_factory.mktemp("seneca")
    crop = crop_raster(ortho, CROP, folder / "ortho_crop.tif")
    return build_map(crop, folder / "map", Camera.from_json(camera), TilingConfig(65.0), progress=False)


@pytest.fixture(scope="module")
def dsm_crop(seneca_dsm: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Seneca's DSM over the crop and MARGIN_M around it."""
    left, bottom, right, top = CROP
    bounds = (left - MARGIN_M, bottom - MARGIN_M, right + MARGIN_M, top + MARGIN_M)
    return crop_raster(seneca_dsm, bounds, tmp_path_factory.mktemp("dsm") / "dsm_crop.tif")


@pytest.fixture(scope="module")
def seneca_terrain(seneca_map: MapPackage, seneca_dsm: Path, tmp_path_factory: pytest.TempPathFactory):
    return attach_terrain(copy_map(seneca_map, tmp_path_factory.mktemp("attached")), seneca_dsm)


def test_seneca_heights_agree_with_the_dsm(seneca_terrain: MapPackage, seneca_dsm: Path) -> None:
    terrain = seneca_terrain.terrain
    assert terrain is not None
    points = smooth_points(seneca_terrain, seneca_dsm)
    np.testing.assert_allclose(
        terrain.heights_at(points), dsm_heights(seneca_dsm, seneca_terrain, points), atol=0.2
    )
    # Everywhere (trees and roof edges included) the heights are the DSM's, resampled.
    rng = np.random.default_rng(0)
    anywhere = rng.uniform(0, [seneca_terrain.grid.width, seneca_terrain.grid.height], (500, 2))
    error = np.abs(terrain.heights_at(anywhere) - dsm_heights(seneca_dsm, seneca_terrain, anywhere))
    assert np.median(error) < 0.05
    record = seneca_terrain.manifest["terrain"]
    assert record["max_m"] - record["min_m"] > 10.0  # the trees and the house: relief, not flat
    assert 205.0 < terrain.median_m < 230.0
    assert record["unknown_frac"] == 0.0 and record["vertical_units"] == "m"
    assert record["source"] == "dsm.tif" and record["source_crs"] == "EPSG:32617"
    assert terrain.datum == "the DSM's vertical datum (source: dsm.tif)"
    assert terrain.summary()["datum"] == terrain.datum
    assert seneca_terrain.summary()["terrain"].startswith("dsm.tif: 0.0 % of the cells filled")


def test_heights_outside_the_map_are_nan(seneca_terrain: MapPackage) -> None:
    grid = seneca_terrain.grid
    heights = seneca_terrain.terrain.heights_at(
        np.array([[-5.0, 10.0], [grid.width + 5.0, 10.0], [10.0, 10.0]])
    )
    assert np.isnan(heights[:2]).all() and np.isfinite(heights[2])
    assert seneca_terrain.terrain.heights_at(np.zeros((0, 2))).shape == (0,)


@pytest.mark.parametrize("crs", ["EPSG:4326", "EPSG:3857"])
def test_a_dsm_in_another_crs_gives_the_same_heights(
    seneca_terrain: MapPackage, seneca_map: MapPackage, dsm_crop: Path, crs: str, tmp_path: Path
) -> None:
    other = reproject_dsm(dsm_crop, crs, tmp_path / "dsm_other.tif")
    package = attach_terrain(copy_map(seneca_map, tmp_path), other)
    points = smooth_points(seneca_terrain, dsm_crop)
    expected = seneca_terrain.terrain.heights_at(points)
    np.testing.assert_allclose(package.terrain.heights_at(points), expected, atol=0.3)
    assert package.manifest["terrain"]["source_crs"] == crs


def test_holes_are_filled_and_reported(seneca_map: MapPackage, dsm_crop: Path, tmp_path: Path) -> None:
    heights, profile = read_dsm(dsm_crop)
    cell = profile["transform"].a
    hole = slice(int(30 / cell), int(40 / cell))  # 10 x 10 m inside the map
    heights[hole, hole] = -9999.0
    holed = write_dsm(tmp_path / "holed.tif", heights, profile["crs"], profile["transform"])
    package = attach_terrain(copy_map(seneca_map, tmp_path), holed)
    record = package.manifest["terrain"]
    assert record["cells_filled_frac"] == pytest.approx(100.0 / 3600.0, abs=0.01)
    assert record["unknown_frac"] == 0.0
    x, y = profile["transform"] @ (np.full(5, hole.start + 25.0), np.linspace(hole.start, hole.stop, 5))
    inside = np.column_stack(package.grid.crs_to_pixel(x, y))
    filled = package.terrain.heights_at(inside)
    assert np.all((filled > record["min_m"] - 0.01) & (filled < record["max_m"] + 0.01))
    assert package.terrain.summary()["cells_filled"] == f"{100 * record['cells_filled_frac']:.1f} %"


def test_a_dsm_missing_most_of_the_map_is_refused(
    seneca_map: MapPackage, dsm_crop: Path, tmp_path: Path
) -> None:
    heights, profile = read_dsm(dsm_crop)
    heights[:, : int(heights.shape[1] * 0.85)] = -9999.0  # only a strip along the east edge
    strip = write_dsm(tmp_path / "strip.tif", heights, profile["crs"], profile["transform"])
    package = copy_map(seneca_map, tmp_path)
    expect_error(lambda: attach_terrain(package, strip, max_fill_m=5.0), "strip.tif", "have no height")
    assert package.terrain is None and not (package.path / "terrain.tif").exists()


def test_a_dsm_off_the_map_is_refused(seneca_map: MapPackage, dsm_crop: Path, tmp_path: Path) -> None:
    heights, profile = read_dsm(dsm_crop)
    far = write_dsm(
        tmp_path / "far.tif", heights, profile["crs"], profile["transform"] @ Affine.translation(25000, 0)
    )
    expect_error(
        lambda: attach_terrain(copy_map(seneca_map, tmp_path), far), "far.tif", "does not overlap the map"
    )


@pytest.mark.parametrize("crs", ["EPSG:32617+6360", "EPSG:3734"])  # NAVD88 height (ftUS); Ohio North (ftUS)
def test_heights_in_feet_are_refused(
    seneca_map: MapPackage, dsm_crop: Path, crs: str, tmp_path: Path
) -> None:
    if "+" in crs:
        heights, profile = read_dsm(dsm_crop)
        feet = write_dsm(
            tmp_path / "feet.tif", heights / 0.3048006, RioCRS.from_user_input(crs), profile["transform"]
        )
    else:
        feet = reproject_dsm(dsm_crop, crs, tmp_path / "feet.tif")
    expect_error(
        lambda: attach_terrain(copy_map(seneca_map, tmp_path), feet), "feet.tif", "expected heights in metres"
    )


@pytest.mark.parametrize(
    ("scale", "nodata"), [(1000.0, -9999.0), (0.0, None)]
)  # millimetres; all 0 * x - 32768
def test_implausible_heights_are_refused(
    seneca_map: MapPackage, dsm_crop: Path, scale: float, nodata: float | None, tmp_path: Path
) -> None:
    heights, profile = read_dsm(dsm_crop)
    bad = heights * scale if scale else np.full_like(heights, -32768.0)
    path = write_dsm(tmp_path / "bad.tif", bad, profile["crs"], profile["transform"], nodata=nodata)
    expect_error(lambda: attach_terrain(copy_map(seneca_map, tmp_path), path), "bad.tif", "not plausible")


def test_unreadable_dsm_files_are_named(seneca_map: MapPackage, tmp_path: Path) -> None:
    package = copy_map(seneca_map, tmp_path)
    expect_error(lambda: attach_terrain(package, tmp_path / "none.tif"), "none.tif", "no such file")
    (tmp_path / "text.tif").write_text("not a raster")
    expect_error(lambda: attach_terrain(package, tmp_path / "text.tif"), "text.tif", "not a readable")


def test_reattaching_replaces_the_terrain(seneca_terrain: MapPackage, dsm_crop: Path, tmp_path: Path) -> None:
    package = copy_map(seneca_terrain, tmp_path)
    before = package.manifest["terrain"]
    heights, profile = read_dsm(dsm_crop)
    raised = write_dsm(tmp_path / "raised.tif", heights + 100.0, profile["crs"], profile["transform"])
    again = attach_terrain(package, raised)
    assert again.manifest["terrain"]["source"] == "raised.tif"
    assert again.terrain.median_m == pytest.approx(before["median_m"] + 100.0, abs=0.05)
    assert {p.name for p in again.path.glob("*terrain*")} == {"terrain.tif"}


def test_a_damaged_terrain_file_is_named(seneca_terrain: MapPackage, tmp_path: Path) -> None:
    package = copy_map(seneca_terrain, tmp_path)
    with open(package.path / "terrain.tif", "r+b") as fh:
        fh.seek(-64, 2)
        fh.write(b"\0" * 64)
    expect_error(
        lambda: MapPackage(package.path).terrain.heights_at(np.ones((1, 2))), "terrain.tif", "re-attach"
    )


def test_a_package_without_terrain_is_flat_ground(seneca_map: MapPackage) -> None:
    assert seneca_map.terrain is None
    assert seneca_map.summary()["terrain"] == "none (flat ground)"


def test_cli_attaches_terrain_in_one_line(seneca_map: MapPackage, seneca_dsm: Path, tmp_path: Path) -> None:
    package = copy_map(seneca_map, tmp_path)
    result = runner.invoke(app, ["map", "terrain", str(package.path), str(seneca_dsm)])
    assert result.exit_code == 0, result.output
    line = [row for row in result.output.splitlines() if "% of the cells filled" in row]
    assert len(line) == 1 and "unknown" in line[0] and "heights" in line[0], result.output
    assert MapPackage(package.path).terrain is not None
    info = runner.invoke(app, ["map", "info", str(package.path), "--json"])
    assert json.loads(info.output)["terrain"].startswith("dsm.tif:")
    bad = runner.invoke(app, ["map", "terrain", str(package.path), str(tmp_path / "nope.tif")])
    assert isinstance(bad.exception, OrthonavError) and "nope.tif" in str(bad.exception)


def test_cli_builds_a_map_with_terrain(seneca_map: MapPackage, dsm_crop: Path, tmp_path: Path) -> None:
    camera = shared_file(f"{SENECA}/camera.json")
    args = [
        "map",
        "build",
        str(seneca_map.source_path),
        "--out",
        str(tmp_path / "map"),
        "--camera",
        str(camera),
    ]
    result = runner.invoke(app, [*args, "--altitude", "65", "--dsm", str(dsm_crop)])
    assert result.exit_code == 0, result.output
    package = MapPackage(tmp_path / "map")
    assert package.manifest["terrain"]["source"] == "dsm_crop.tif"
    assert not (tmp_path / "map.partial").exists()
    early = runner.invoke(app, [*args, "--overwrite", "--dsm", str(tmp_path / "none.tif")])
    assert isinstance(early.exception, OrthonavError) and "none.tif" in str(early.exception)
    assert not (tmp_path / "map.partial").exists()  # refused before the build started


# --- synthetic: the pixel convention, corridors -------------------------------------------------


@pytest.fixture(scope="module")
def plane_map(tmp_path_factory: pytest.TempPathFactory) -> MapPackage:
    """A 512 m synthetic map (16 tiles) with a planar DSM at 2 m cells under it."""
    folder = tmp_path_factory.mktemp("plane")
    ortho = write_terrain_geotiff(folder / "ortho.tif", TerrainConfig(size_px=512, gsd_m=1.0))
    package = build_map(ortho, folder / "map", SMALL_CAM, SMALL_TILING, progress=False)
    with rasterio.open(ortho) as ds:
        crs, left, top = ds.crs, ds.bounds.left, ds.bounds.top
    rows, cols = np.mgrid[0:270, 0:270] + 0.5
    x, y = cols * 2.0 - 10.0, -(rows * 2.0 - 10.0)  # 10 m beyond the map on each side
    a, b, c = PLANE
    dsm = write_dsm(
        folder / "plane.tif", a * x + b * y + c, crs, Affine(2.0, 0, left - 10.0, 0, -2.0, top + 10.0)
    )
    return attach_terrain(package, dsm)


def plane_height(package: MapPackage, map_px: np.ndarray) -> np.ndarray:
    xs, ys = package.grid.pixel_to_crs(map_px[:, 0], map_px[:, 1])
    x0, y0 = package.grid.pixel_to_crs(0, 0)
    a, b, c = PLANE
    return a * (xs - x0) + b * (ys - y0) + c


def test_heights_follow_a_plane_exactly(plane_map: MapPackage) -> None:
    """Bilinear interpolation reproduces a plane: any offset in the pixel convention shows."""
    grid = plane_map.grid
    rng = np.random.default_rng(2)
    points = rng.uniform(1, [grid.width - 1, grid.height - 1], (400, 2))  # not in the edges' half cells
    np.testing.assert_allclose(
        plane_map.terrain.heights_at(points), plane_height(plane_map, points), atol=1e-3
    )
    assert plane_map.manifest["terrain"]["cell_work_px"] == 1  # the work grid is coarser than the DSM


def test_a_corridor_keeps_the_terrain_under_it(plane_map: MapPackage, tmp_path: Path) -> None:
    lat, lon = plane_map.grid.pixel_to_latlon([40.0, 40.0], [40.0, plane_map.grid.height - 40.0])
    route = list(zip(lat.tolist(), lon.tolist(), strict=True))
    corridor = cut_corridor(plane_map, route, 60.0, tmp_path / "corridor")
    assert 0 < len(corridor) < len(plane_map) and corridor.terrain is not None
    rng = np.random.default_rng(3)
    points = rng.uniform(0, [corridor.grid.width, corridor.grid.height], (400, 2))
    xs, ys = corridor.grid.pixel_to_crs(points[:, 0], points[:, 1])
    parent_px = np.column_stack(plane_map.grid.crs_to_pixel(xs, ys))
    on_map = np.all(
        (parent_px > 1) & (parent_px < [plane_map.grid.width - 1, plane_map.grid.height - 1]), axis=1
    )
    points, parent_px = points[on_map], parent_px[on_map]  # padded tiles reach beyond the map
    heights = corridor.terrain.heights_at(points)
    np.testing.assert_allclose(heights, plane_map.terrain.heights_at(parent_px), atol=1e-4)
    assert np.isfinite(heights).all()
    assert corridor.manifest["terrain"]["width"] < plane_map.manifest["terrain"]["width"]


def test_bilinear_between_known_cells() -> None:
    grid = np.array([[0.0, 1.0], [2.0, np.nan]])
    cols, rows = np.array([0.5, 1.0, 0.75, 2.5, 1.5]), np.array([0.5, 0.5, 0.5, 0.5, 1.5])
    out = bilinear(grid, cols, rows)
    np.testing.assert_allclose(out[:3], [0.0, 0.5, 0.25])
    assert np.isnan(out[3]) and np.isnan(out[4])  # off the grid; in the unknown cell
    # Three known neighbours of four: weighted among themselves.
    assert bilinear(grid, np.array([0.9]), np.array([0.9]))[0] == pytest.approx(0.72 / 0.84)
