"""Geography: pixel <-> CRS <-> WGS84, geodesics, local ENU frames, GSD, reading rasters."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import rasterio
from affine import Affine
from helpers_geotiff import shared_file, textured, write_geotiff
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pyproj import CRS, Geod, Transformer

from orthonav.errors import OrthonavError
from orthonav.geo import (
    GeoGrid,
    GeoRaster,
    LocalFrame,
    PixelWindow,
    azimuth_deg,
    bright_pixels,
    check_latlon,
    destination,
    distance_m,
)

REF_GEOD = Geod(ellps="WGS84")


@dataclass(frozen=True)
class GridCase:
    epsg: int
    transform: Affine
    width: int
    height: int
    tol_px: float  # round-trip tolerance


GRIDS = {
    # NAIP quarter-quad, NAD83 / UTM 14N, 5 m.
    "utm26914": GridCase(26914, Affine(5.0, 0, 485899.0, 0, -5.0, 5209246.0), 934, 724, 1e-6),
    # Manila, World Mercator, 0.1 CRS units.
    "mercator3395": GridCase(3395, Affine(0.1, 0, 13467532.0, 0, -0.1, 1632019.88), 2048, 2048, 1e-6),
    # Geographic degrees, North Dakota.
    "wgs84": GridCase(4326, Affine(1e-5, 0, -99.2, 0, -1e-5, 47.05), 1000, 800, 1e-6),
    # Dutch RD New: Bessel datum; pyproj's WGS84 <-> RD Helmert pair is inverse only to ~0.5 mm.
    "rd28992": GridCase(28992, Affine(0.25, 0, 127375.0, 0, -0.25, 428250.0), 1000, 1000, 1e-2),
}


def make_grid(case: GridCase) -> GeoGrid:
    return GeoGrid(CRS.from_epsg(case.epsg), case.transform, case.width, case.height)


def angle_diff(a: float, b: float) -> float:
    """Smallest absolute difference of two angles in degrees."""
    return abs((a - b + 180.0) % 360.0 - 180.0)


# --- pixel <-> CRS <-> WGS84 ------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(GRIDS))
@settings(max_examples=40, deadline=None)
@given(u=st.floats(-1.0, 2.0), v=st.floats(-1.0, 2.0))
def test_pixel_crs_latlon_round_trip(name: str, u: float, v: float) -> None:
    """pixel -> CRS -> pixel and pixel -> WGS84 -> pixel return the start, on and off the grid."""
    case = GRIDS[name]
    grid = make_grid(case)
    col, row = u * case.width, v * case.height
    x, y = grid.pixel_to_crs(col, row)
    ex, ey = case.transform @ (col, row)
    assert float(x) == pytest.approx(ex, abs=1e-6) and float(y) == pytest.approx(ey, abs=1e-6)
    c2, r2 = grid.crs_to_pixel(x, y)
    assert abs(float(c2) - col) < 1e-6 and abs(float(r2) - row) < 1e-6
    lat, lon = grid.pixel_to_latlon(col, row)
    c3, r3 = grid.latlon_to_pixel(lat, lon)
    assert abs(float(c3) - col) < case.tol_px and abs(float(r3) - row) < case.tol_px


@pytest.mark.parametrize("name", sorted(GRIDS))
def test_pixel_to_latlon_matches_pyproj(name: str) -> None:
    """pixel_to_latlon agrees with a fresh pyproj transformer applied to the affine transform."""
    case = GRIDS[name]
    grid = make_grid(case)
    rng = np.random.default_rng(1)
    cols = rng.uniform(0, case.width, 50)
    rows = rng.uniform(0, case.height, 50)
    xs, ys = case.transform @ (cols, rows)
    lon_ref, lat_ref = Transformer.from_crs(case.epsg, 4326, always_xy=True).transform(xs, ys)
    lat, lon = grid.pixel_to_latlon(cols, rows)
    np.testing.assert_allclose(lat, lat_ref, rtol=0, atol=1e-10)
    np.testing.assert_allclose(lon, lon_ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("name", sorted(GRIDS))
def test_gsd_is_geodesic_distance_between_pixel_centres(name: str) -> None:
    """gsd_xy_m is the WGS84 geodesic length of one pixel step at the grid centre."""
    case = GRIDS[name]
    grid = make_grid(case)
    c, r = case.width / 2, case.height / 2
    to_wgs = Transformer.from_crs(case.epsg, 4326, always_xy=True)
    lon, lat = to_wgs.transform(*(case.transform @ (np.array([c, c + 1, c]), np.array([r, r, r + 1]))))
    _, _, gx = REF_GEOD.inv(lon[0], lat[0], lon[1], lat[1])
    _, _, gy = REF_GEOD.inv(lon[0], lat[0], lon[2], lat[2])
    assert grid.gsd_xy_m == pytest.approx((gx, gy), rel=1e-9)
    assert grid.gsd_m == pytest.approx((gx + gy) / 2, rel=1e-9)


def test_scaled_grid_covers_same_area() -> None:
    """scaled(f) keeps the origin and the extent (to a pixel) with f-times larger pixels."""
    grid = make_grid(GRIDS["utm26914"])
    coarse = grid.scaled(3.0)
    assert coarse.transform.a == pytest.approx(3 * grid.transform.a)
    assert coarse.transform.e == pytest.approx(3 * grid.transform.e)
    assert (coarse.transform.c, coarse.transform.f) == (grid.transform.c, grid.transform.f)
    x_end, y_end = grid.pixel_to_crs(grid.width, grid.height)
    cx_end, cy_end = coarse.pixel_to_crs(coarse.width, coarse.height)
    assert abs(float(cx_end - x_end)) <= coarse.transform.a / 2 + 1e-9
    assert abs(float(cy_end - y_end)) <= abs(coarse.transform.e) / 2 + 1e-9


def test_contains_latlon() -> None:
    """The centre is on the grid, a point 10 km beyond the east edge is not (unless the margin allows)."""
    grid = make_grid(GRIDS["utm26914"])
    lat, lon = grid.center_latlon
    assert grid.contains_latlon(lat, lon)
    lat_e, lon_e = grid.pixel_to_latlon(grid.width, grid.height / 2)
    far_lat, far_lon = destination(float(lat_e), float(lon_e), 90.0, 10_000.0)
    assert not grid.contains_latlon(far_lat, far_lon)
    assert grid.contains_latlon(far_lat, far_lon, margin_px=10_000.0 / 5.0 + 10)


# --- geodesics ---------------------------------------------------------------------------------

lats = st.floats(-80.0, 80.0)
lons = st.floats(-180.0, 180.0)


@settings(max_examples=60, deadline=None)
@given(lat=lats, lon=lons, az=st.floats(0.0, 359.999), dist=st.floats(1.0, 1_000_000.0))
def test_destination_then_inverse_returns_inputs(lat: float, lon: float, az: float, dist: float) -> None:
    """Flying dist on az then measuring back gives the same distance and azimuth."""
    lat2, lon2 = destination(lat, lon, az, dist)
    ref_lon, ref_lat, _ = REF_GEOD.fwd(lon, lat, az, dist)
    assert lat2 == pytest.approx(ref_lat, abs=1e-9)
    assert angle_diff(lon2, ref_lon) < 1e-9
    assert float(distance_m(lat, lon, lat2, lon2)) == pytest.approx(dist, rel=1e-9, abs=1e-6)
    assert angle_diff(float(azimuth_deg(lat, lon, lat2, lon2)), az) < 1e-6


@settings(max_examples=40, deadline=None)
@given(lat1=lats, lon1=lons, lat2=lats, lon2=lons)
def test_distance_and_azimuth_match_pyproj(lat1: float, lon1: float, lat2: float, lon2: float) -> None:
    """distance_m/azimuth_deg equal pyproj.Geod.inv; azimuth normalised to [0, 360)."""
    az_ref, _, dist_ref = REF_GEOD.inv(lon1, lat1, lon2, lat2)
    assert float(distance_m(lat1, lon1, lat2, lon2)) == pytest.approx(dist_ref, rel=1e-12, abs=1e-9)
    az = float(azimuth_deg(lat1, lon1, lat2, lon2))
    assert 0.0 <= az < 360.0
    assert angle_diff(az, az_ref) < 1e-9


def test_azimuth_a_hair_west_of_north_is_not_360() -> None:
    """The range is [0, 360): a tiny negative azimuth wraps to ~0, not to 360.0 (float rounding)."""
    az = float(azimuth_deg(0.0, 0.0, 1.0, -2.220446049250313e-16))
    assert 0.0 <= az < 360.0
    assert angle_diff(az, 0.0) < 1e-9
    arr = azimuth_deg(
        np.array([0.0, -1.0]), np.array([0.0, 2.2e-16]), np.array([1.0, 0.0]), np.array([-2.2e-16, 0.0])
    )
    assert np.all((arr >= 0.0) & (arr < 360.0))


def test_geodesics_vectorised() -> None:
    """Arrays in, arrays out, element by element equal to the scalar calls."""
    lat1 = np.array([10.0, 47.0, -33.0])
    lon1 = np.array([20.0, -99.0, 18.0])
    lat2 = lat1 + 0.01
    lon2 = lon1 - 0.02
    d = distance_m(lat1, lon1, lat2, lon2)
    a = azimuth_deg(lat1, lon1, lat2, lon2)
    assert d.shape == (3,) and a.shape == (3,)
    for i in range(3):
        assert d[i] == pytest.approx(float(distance_m(lat1[i], lon1[i], lat2[i], lon2[i])))
        # north-west-ish: between 270 and 360
        assert 270.0 < a[i] < 360.0


@pytest.mark.parametrize(
    ("lat", "lon", "what"),
    [
        (math.nan, 0.0, "finite"),
        (0.0, math.nan, "finite"),
        (math.inf, 0.0, "finite"),
        (0.0, -math.inf, "finite"),
        (90.0001, 0.0, "latitude"),
        (-91.0, 0.0, "latitude"),
        (0.0, 180.5, "longitude"),
        (0.0, -181.0, "longitude"),
    ],
)
def test_check_latlon_rejects(lat: float, lon: float, what: str) -> None:
    """Non-finite or out-of-range positions raise OrthonavError naming the field and the problem."""
    with pytest.raises(OrthonavError) as exc:
        check_latlon(lat, lon, field="home point")
    assert "home point" in str(exc.value)
    assert what in str(exc.value)


@pytest.mark.parametrize(("lat", "lon"), [(90.0, 180.0), (-90.0, -180.0), (0.0, 0.0), (47.1, -99.2)])
def test_check_latlon_accepts_valid(lat: float, lon: float) -> None:
    """Valid positions, including the limits, pass; the function signals only by raising."""
    assert check_latlon(lat, lon) is None


# --- local ENU frame ---------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    lat0=st.floats(-75.0, 75.0),
    lon0=st.floats(-179.0, 179.0),
    az=st.floats(0.0, 359.999),
    dist=st.floats(0.0, 20_000.0),
)
@example(lat0=66.0, lon0=0.0, az=66.0, dist=0.0005)  # snapped onto the origin at 66 deg N
def test_local_frame_is_azimuthal_equidistant(lat0: float, lon0: float, az: float, dist: float) -> None:
    """A point dist metres away on az maps to (dist sin az, dist cos az), and back to itself."""
    frame = LocalFrame(lat0, lon0)
    lat, lon = destination(lat0, lon0, az, dist)
    east, north = frame.to_enu(lat, lon)
    a = math.radians(az)
    assert float(east) == pytest.approx(dist * math.sin(a), abs=1e-3)
    assert float(north) == pytest.approx(dist * math.cos(a), abs=1e-3)
    lat2, lon2 = frame.to_latlon(east, north)
    # The round trip is bounded on the ground, not in degrees: PROJ's aeqd inverse snaps points
    # within ~0.6 mm of the origin onto it, and 0.6 mm is more degrees of longitude near the poles.
    _, _, back_m = REF_GEOD.inv(lon, lat, float(lon2), float(lat2))
    assert back_m < 1e-3


def test_local_frame_1000m_east() -> None:
    """destination(..., 90 deg, 1000 m) is (1000, 0) m in the frame at the start point."""
    frame = LocalFrame(50.45, 30.52)
    lat, lon = destination(50.45, 30.52, 90.0, 1000.0)
    east, north = frame.to_enu(lat, lon)
    assert float(east) == pytest.approx(1000.0, abs=1e-3)
    assert float(north) == pytest.approx(0.0, abs=1e-3)
    e0, n0 = frame.to_enu(50.45, 30.52)
    assert abs(float(e0)) < 1e-6 and abs(float(n0)) < 1e-6


def test_local_frame_from_crs_matches_latlon_path() -> None:
    """from_crs(UTM) equals to_enu of the same point converted to WGS84 with pyproj directly."""
    frame = LocalFrame(47.05, -99.18)
    xs = np.array([486000.0, 487500.0, 489000.0])
    ys = np.array([5209000.0, 5207000.0, 5205500.0])
    lon, lat = Transformer.from_crs(26914, 4326, always_xy=True).transform(xs, ys)
    e_ref, n_ref = frame.to_enu(lat, lon)
    east, north = frame.from_crs(CRS.from_epsg(26914), xs, ys)
    np.testing.assert_allclose(east, e_ref, atol=1e-6)
    np.testing.assert_allclose(north, n_ref, atol=1e-6)


def test_local_frame_equals_pyproj_aeqd_crs() -> None:
    """The frame's pipeline gives what pyproj's own WGS84 <-> aeqd CRS transformer gives, both ways."""
    lat0, lon0 = 47.1019, -99.2
    aeqd = CRS.from_proj4(f"+proj=aeqd +lat_0={lat0} +lon_0={lon0} +datum=WGS84 +units=m")
    reference = Transformer.from_crs(CRS.from_epsg(4326), aeqd, always_xy=True)
    east = np.array([0.0, 1000.0, -2500.3, 7000.0])
    north = np.array([0.0, 2000.0, 1234.5, -6000.0])
    frame = LocalFrame(lat0, lon0)
    lat, lon = frame.to_latlon(east, north)
    ref_lon, ref_lat = reference.transform(east, north, direction="INVERSE")
    np.testing.assert_allclose(lat, ref_lat, atol=1e-10)
    np.testing.assert_allclose(lon, ref_lon, atol=1e-10)
    np.testing.assert_allclose(
        np.column_stack(frame.to_enu(lat, lon)), np.column_stack([east, north]), atol=1e-6
    )


def test_local_frame_rejects_bad_origin() -> None:
    """An impossible origin is a user error, not a PROJ crash."""
    with pytest.raises(OrthonavError):
        LocalFrame(95.0, 0.0)
    with pytest.raises(OrthonavError):
        LocalFrame.at(95.0, 0.0)


def test_shared_local_frame_is_the_frame_at_that_exact_origin() -> None:
    """``LocalFrame.at`` gives one frame per origin, the same numbers as a new frame there (not
    the ~8 km shared origin of ``around``)."""
    lat0, lon0 = 47.0512345, -99.1876543
    shared = LocalFrame.at(lat0, lon0)
    assert LocalFrame.at(lat0, lon0) is shared
    assert (shared.lat0, shared.lon0) == (lat0, lon0)
    east, north = np.array([0.0, 850.0, -1200.0]), np.array([0.0, -430.0, 975.0])
    np.testing.assert_array_equal(
        np.column_stack(shared.to_latlon(east, north)),
        np.column_stack(LocalFrame(lat0, lon0).to_latlon(east, north)),
    )


# --- real orthophotos --------------------------------------------------------------------------


def expected_gsd_xy(path: Path) -> tuple[float, float]:
    """Geodesic distance between neighbouring pixel centres at the raster centre, via pyproj."""
    with rasterio.open(path) as ds:
        t, crs, w, h = ds.transform, CRS.from_user_input(ds.crs), ds.width, ds.height
    cols = np.array([w / 2, w / 2 + 1, w / 2])
    rows = np.array([h / 2, h / 2, h / 2 + 1])
    lon, lat = Transformer.from_crs(crs, 4326, always_xy=True).transform(*(t @ (cols, rows)))
    gx = REF_GEOD.inv(lon[0], lat[0], lon[1], lat[1])[2]
    gy = REF_GEOD.inv(lon[0], lat[0], lon[2], lat[2])[2]
    return gx, gy


def test_manila_world_mercator_gsd_is_true_ground_metres() -> None:
    """EPSG:3395 units are stretched by 1/cos(lat): 0.1 units at 14.6 N are ~0.0968 m on the ground."""
    path = shared_file("highres/oam_manila_10cm.tif")
    with GeoRaster(path) as raster:
        assert raster.crs.to_epsg() == 3395
        assert raster.transform.a == pytest.approx(0.1, rel=1e-2)
        gx, gy = expected_gsd_xy(path)
        assert raster.gsd_xy_m == pytest.approx((gx, gy), rel=1e-9)
        assert raster.gsd_m < 0.099
        assert raster.gsd_m == pytest.approx(0.0968, abs=0.0003)
        lat, _ = raster.center_latlon
        assert 14.0 < lat < 15.0  # Manila


@pytest.mark.parametrize(
    ("relative", "nominal"),
    [("highres/nl_aerial_25cm.tif", 0.25), ("naip/m_4709963_se_14_1_20200831.tif", 5.0)],
)
def test_real_rasters_gsd(relative: str, nominal: float) -> None:
    """Projected grids with scale factor ~1 give a GSD within 0.1 % of their nominal pixel size."""
    path = shared_file(relative)
    with GeoRaster(path) as raster:
        assert raster.gsd_xy_m == pytest.approx(expected_gsd_xy(path), rel=1e-9)
        assert raster.gsd_m == pytest.approx(nominal, rel=1e-3)
        rgb = raster.read_rgb(PixelWindow(0, 0, 64, 48))
        assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8
        assert rgb.std() > 1.0  # real imagery, not a blank read


def test_a_crop_of_a_ycbcr_jpeg_orthophoto_keeps_its_pixels_and_place(tmp_path: Path) -> None:
    """Photogrammetry tools write YCbCr-in-JPEG orthophotos (Seneca's); the crop a corridor cut
    writes is deflate-compressed, so it must be RGB, with the source's pixels and georeferencing."""
    path = shared_file("real/seneca/ortho.tif")
    with GeoRaster(path) as raster:
        assert raster._ds.profile["photometric"] == "ycbcr"
        left, top = raster.transform @ (3000, 4000)
        right, bottom = raster.transform @ (3400, 4300)
        out = raster.crop_to((left, bottom, right, top), tmp_path / "crop.tif")
        source = raster._ds.read(window=rasterio.windows.Window(3000, 4000, 400, 300))
    with rasterio.open(out) as crop:
        assert crop.shape == (300, 400) and crop.transform.almost_equals(
            raster.transform @ Affine.translation(3000, 4000)
        )
        assert np.array_equal(crop.read(), source)


# --- reading pixels ----------------------------------------------------------------------------


def test_read_rgb_gray_file_is_replicated(tmp_path: Path) -> None:
    """A 1-band file reads as (H, W, 3) uint8 with three identical channels equal to the band."""
    data = textured(40, 56, bands=1)
    with GeoRaster(write_geotiff(tmp_path / "gray.tif", data)) as raster:
        rgb = raster.read_rgb()
    assert rgb.shape == (40, 56, 3) and rgb.dtype == np.uint8
    for ch in range(3):
        np.testing.assert_array_equal(rgb[..., ch], data[0])


@pytest.mark.parametrize("bands", [3, 4])
def test_read_rgb_colour_files(tmp_path: Path, bands: int) -> None:
    """3- and 4-band uint8 files read as their first three bands, unchanged, as (H, W, 3)."""
    data = textured(40, 56, bands=bands, seed=bands)
    with GeoRaster(write_geotiff(tmp_path / "rgb.tif", data)) as raster:
        assert raster.band_count == bands
        rgb = raster.read_rgb()
    assert rgb.shape == (40, 56, 3) and rgb.dtype == np.uint8
    np.testing.assert_array_equal(rgb, np.moveaxis(data[:3], 0, -1))


def test_read_rgb_uint16_is_stretched(tmp_path: Path) -> None:
    """uint16 imagery is stretched monotonically to use most of 0..255."""
    rng = np.random.default_rng(5)
    data = rng.integers(1000, 4000, size=(3, 64, 64)).astype(np.uint16)
    with GeoRaster(write_geotiff(tmp_path / "u16.tif", data)) as raster:
        assert raster.dtype == "uint16"
        rgb = raster.read_rgb()
    assert rgb.shape == (64, 64, 3) and rgb.dtype == np.uint8
    lo, hi = np.percentile(rgb, [1, 99])
    assert lo <= 5 and hi >= 250
    band = data[0].ravel()
    out = rgb[..., 0].ravel()
    order = np.argsort(band, kind="stable")
    assert np.all(np.diff(out[order].astype(int)) >= 0), "stretch must preserve brightness order"


def test_read_rgb_window_outside_and_resampled(tmp_path: Path) -> None:
    """Window pixels beyond the raster are 0; out_shape averages 2x2 blocks."""
    data = textured(64, 64, bands=3, seed=9)
    with GeoRaster(write_geotiff(tmp_path / "w.tif", data)) as raster:
        part = raster.read_rgb(PixelWindow(-8, -4, 32, 32))
        half = raster.read_rgb(out_shape=(32, 32))
    assert part.shape == (32, 32, 3)
    assert not part[:4].any() and not part[:, :8].any()
    np.testing.assert_array_equal(part[4:, 8:], np.moveaxis(data[:, :28, :24], 0, -1))
    blocks = np.moveaxis(data, 0, -1).astype(float).reshape(32, 2, 32, 2, 3).mean(axis=(1, 3))
    assert half.shape == (32, 32, 3)
    assert np.abs(half.astype(float) - blocks).max() <= 1.0


def test_read_rgb_nodata_pixels_are_zero(tmp_path: Path) -> None:
    """Pixels equal to the nodata value in every band read as 0, whatever the nodata value is."""
    data = textured(48, 48, bands=3, seed=2)  # texture values stay in 20..235
    data[:, :, :12] = 255
    with GeoRaster(write_geotiff(tmp_path / "nd.tif", data, nodata=255)) as raster:
        rgb = raster.read_rgb()
    assert not rgb[:, :12].any()
    np.testing.assert_array_equal(rgb[:, 12:], np.moveaxis(data[:, :, 12:], 0, -1))


def test_read_grid_box_on_the_work_grid_and_on_another_grid(tmp_path: Path) -> None:
    """A box of a scaled grid reads the source window times the factor; a box of an unrelated
    grid of the same CRS reads the same ground through its coordinates; another CRS is refused."""
    data = textured(96, 96, bands=3, seed=4)
    with GeoRaster(write_geotiff(tmp_path / "g.tif", data)) as raster:
        work = raster.scaled(1.5)
        assert raster.scale_factor_of(work) == pytest.approx(1.5)
        box = (4, 6, 36, 30)
        exact = raster.read_rgb(PixelWindow(6, 9, 48, 36), out_shape=(24, 32))
        np.testing.assert_array_equal(raster.read_grid_box(work, box), exact)
        t = raster.transform
        origin = Affine.translation(t.c + 10 * t.a, t.f + 5 * t.e)
        shifted = GeoGrid(raster.crs, origin @ Affine.scale(t.a, t.e), 80, 80)
        assert raster.scale_factor_of(shifted) is None
        np.testing.assert_array_equal(
            raster.read_grid_box(shifted, (0, 0, 20, 20)),
            raster.read_rgb(PixelWindow(10, 5, 20, 20), (20, 20)),
        )
        other = GeoGrid(CRS.from_epsg(3857), raster.transform, 96, 96)
        with pytest.raises(OrthonavError, match="grid CRS"):
            raster.read_grid_box(other, box)


@pytest.mark.parametrize(
    "gsd_m, level, max_mean_diff", [(5.0, 1, 0.0), (7.0, 1, 0.5), (12.0, 2, 3.0), (23.0, 4, 3.0)]
)
def test_views_cut_from_memory_match_views_read_from_the_file(
    gsd_m: float, level: int, max_mean_diff: float
) -> None:
    """A view cut from the in-memory copy of a NAIP raster is the file's own view: the same pixels
    where no averaging is needed, within a few grey levels where the two average differently."""
    path = shared_file("naip/m_4709963_se_14_1_20200831.tif")
    with GeoRaster(path) as cached, GeoRaster(path, view_cache_bytes=0) as direct:
        assert cached._view_level(gsd_m / cached.gsd_m) == level
        assert direct._view_level(gsd_m / direct.gsd_m) is None
        lat, lon = cached.pixel_to_latlon(0.8 * cached.width, 0.5 * cached.height)  # reaching off the map
        frame = LocalFrame(float(lat), float(lon))

        def out_to_latlon(px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            east, north = (px[:, 0] - 200.0) * gsd_m, (150.0 - px[:, 1]) * gsd_m
            turn = math.radians(30.0)
            return frame.to_latlon(
                east * math.cos(turn) - north * math.sin(turn), east * math.sin(turn) + north * math.cos(turn)
            )

        view = cached.read_view(out_to_latlon, 400, 300, gsd_m)
        reference = direct.read_view(out_to_latlon, 400, 300, gsd_m)
    assert (view == 0).all(axis=2).any() and (reference == 0).all(axis=2).any()  # off the map: 0 in both
    assert np.abs(view.astype(float) - reference.astype(float)).mean() <= max_mean_diff


def test_a_negative_view_cache_is_refused_by_name() -> None:
    path = shared_file("naip/m_4709963_se_14_1_20200831.tif")
    with pytest.raises(OrthonavError, match=r"20200831.tif: view_cache_bytes -1: expected bytes >= 0"):
        GeoRaster(path, view_cache_bytes=-1)


@pytest.mark.parametrize("bands", [1, 3, 4])
@pytest.mark.parametrize("above", [0, 8])
def test_bright_pixels_is_the_brightest_band_above(bands: int, above: int) -> None:
    rng = np.random.default_rng(bands + above)
    image = rng.integers(0, 12, (37, 53, bands), dtype=np.uint8)
    image[:5] = 0  # off the map: black in every band
    got = bright_pixels(image, above)
    np.testing.assert_array_equal(got, image.max(axis=2) > above)
    assert got.dtype == bool and not got[:5].any() and got[5:].any()
