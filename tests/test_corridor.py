"""Corridor packages cut from the real NAIP 2020 map: what is kept, self-containment, same fixes."""

from __future__ import annotations

import codecs
import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import CAMERA, NAIP_ALT_M
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, LocalFrame, destination
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage, corridor_tiles, cut_corridor, read_route
from orthonav.types import Prior

WIDTH_M = 1200.0


def write_route(path: Path, route: list[tuple[float, float]]) -> Path:
    feature = {"type": "Feature", "properties": {}, "geometry": {"type": "LineString",
               "coordinates": [[lon, lat] for lat, lon in route]}}  # fmt: skip
    path.write_text(json.dumps(feature))
    return path


@pytest.fixture(scope="module")
def route(naip_raster: GeoRaster) -> list[tuple[float, float]]:
    """West to east through the middle, then north: an L across the map."""
    lat, lon = naip_raster.center_latlon
    west = destination(lat, lon, 270.0, 1500.0)
    east = destination(lat, lon, 90.0, 1200.0)
    return [west, east, destination(*east, 0.0, 1000.0)]


@pytest.fixture(scope="module")
def corridor(naip_map: MapPackage, route, tmp_path_factory) -> MapPackage:
    return cut_corridor(naip_map, route, WIDTH_M, tmp_path_factory.mktemp("corridor") / "small")


def _distance_to_route_m(route: list[tuple[float, float]], lat: float, lon: float) -> float:
    """Point-to-polyline distance in a local metric frame (independent of the code under test)."""
    frame = LocalFrame(lat, lon)
    points = np.array([frame.to_enu(a, b) for a, b in route], float)
    best = np.inf
    for p, q in itertools.pairwise(points):
        t = np.clip(np.dot(-p, q - p) / np.dot(q - p, q - p), 0.0, 1.0)
        best = min(best, float(np.linalg.norm(p + t * (q - p))))
    return best


def test_corridor_keeps_the_tiles_along_the_route_and_drops_the_rest(naip_map: MapPackage, corridor, route):
    kept = corridor_tiles(naip_map, route, WIDTH_M)
    assert len(corridor) == len(kept) < len(naip_map)
    centres = naip_map.tiles.corners_latlon[:, 2]
    half_diagonal_m = naip_map.tile_px * naip_map.gsd_m / np.sqrt(2.0)
    for i, (lat, lon) in enumerate(centres):
        distance = _distance_to_route_m(route, lat, lon)
        if distance <= WIDTH_M / 2:
            assert i in kept, f"tile {i} centre is {distance:.0f} m from the route but was dropped"
        if i in kept:
            assert distance <= WIDTH_M / 2 + half_diagonal_m + naip_map.gsd_m
    # Features are the parent's, tile for tile; map pixels moved onto the cropped grid.
    for new, old in enumerate(kept):
        np.testing.assert_array_equal(
            corridor.tile_features(new).descriptors, naip_map.tile_features(old).descriptors
        )
        lat0, lon0 = naip_map.grid.pixel_to_latlon(*naip_map.tile_keypoints_map_px(old)[:5].T)
        lat1, lon1 = corridor.grid.pixel_to_latlon(*corridor.tile_keypoints_map_px(new)[:5].T)
        np.testing.assert_allclose([lat1, lon1], [lat0, lon0], atol=1e-9)


def test_corridor_package_is_self_contained_and_atomic(corridor: MapPackage, tmp_path: Path) -> None:
    assert not corridor.path.with_name(corridor.path.name + ".partial").exists()
    moved = Path(shutil.move(str(corridor.path), tmp_path / "on-the-drone"))
    try:
        package = MapPackage(moved)  # checksums verified on open
        assert package.source_path == moved / "ortho.tif" and package.source_path.is_file()
        image, _ = package.preview()
        assert image.mean() > 10
        with GeoRaster(package.source_path) as ortho:
            for lat, lon in package.tiles.corners_latlon[:, 2]:
                col, row = ortho.latlon_to_pixel(lat, lon)
                inside = 0 <= col < ortho.width and 0 <= row < ortho.height
                assert inside or package.tiles.padded.any()
        assert package.manifest["corridor"]["width_m"] == WIDTH_M
    finally:
        shutil.move(str(moved), corridor.path)


def test_a_frame_on_the_route_gets_the_same_fix_from_the_corridor(
    naip_map: MapPackage, corridor: MapPackage, naip_raster: GeoRaster, route
) -> None:
    lat, lon = naip_raster.center_latlon
    truth = TruePose(lat, lon, NAIP_ALT_M, 80.0, 1.0, -1.0)
    frame = render_frame(naip_raster, CAMERA, truth, Photometric(), np.random.default_rng(0))
    prior = Prior(*destination(lat, lon, 45.0, 40.0), NAIP_ALT_M, 80.0, 1.0, -1.0, sigma_m=80.0)
    full, small = (
        Localizer(naip_map, CAMERA).localize(frame, prior),
        Localizer(corridor, CAMERA).localize(frame, prior),
    )
    assert full.accepted and small.accepted
    assert (small.pose.lat, small.pose.lon) == pytest.approx((full.pose.lat, full.pose.lon), abs=1e-7)


def test_a_route_saved_with_a_byte_order_mark_reads(route, tmp_path: Path) -> None:
    """Windows editors start UTF-8 files with a byte order mark: the route is read all the same."""
    path = write_route(tmp_path / "route.geojson", route)
    path.write_bytes(codecs.BOM_UTF8 + path.read_bytes())
    assert read_route(path) == read_route(write_route(tmp_path / "plain.geojson", route))


def test_bad_routes_and_outputs_are_named(naip_map: MapPackage, route, tmp_path: Path) -> None:
    far = [(10.0, 10.0), (10.01, 10.01)]
    with pytest.raises(OrthonavError, match="outside the map"):
        cut_corridor(naip_map, far, WIDTH_M, tmp_path / "far")
    assert not (tmp_path / "far").exists() and not (tmp_path / "far.partial").exists()
    (tmp_path / "point.geojson").write_text('{"type": "Point", "coordinates": [-99.1, 47.0]}')
    with pytest.raises(OrthonavError, match="LineString"):
        read_route(tmp_path / "point.geojson")
    swapped = tmp_path / "swapped.geojson"
    swapped.write_text(json.dumps({"type": "LineString", "coordinates": [[47.0, -99.1], [47.0, -99.2]]}))
    with pytest.raises(OrthonavError, match=r"\[lon, lat\]"):
        read_route(swapped)
    with pytest.raises(OrthonavError, match="no such GeoJSON route file"):
        read_route(tmp_path / "missing.geojson")
    with pytest.raises(OrthonavError, match="width"):
        corridor_tiles(naip_map, route, 0.0)
    with pytest.raises(OrthonavError, match="is the map being cut"):
        cut_corridor(naip_map, route, WIDTH_M, naip_map.path, overwrite=True)
    (tmp_path / "a_file").write_text("user data")
    with pytest.raises(OrthonavError, match="a_file: not a folder"):
        cut_corridor(naip_map, route, WIDTH_M, tmp_path / "a_file", overwrite=True)
    assert (tmp_path / "a_file").read_text() == "user data" and not (tmp_path / "a_file.partial").exists()


def test_cli_cuts_a_corridor_and_rejects_a_bad_width(naip_map: MapPackage, route, tmp_path: Path) -> None:
    geojson = write_route(tmp_path / "route.geojson", route)
    runner = CliRunner()
    args = ["map", "corridor", str(naip_map.path), "--route", str(geojson), "--out", str(tmp_path / "c")]
    result = runner.invoke(app, [*args, "--width", "1.2km"])
    assert result.exit_code == 0, result.output
    assert f"of {len(naip_map)} tiles" in result.output
    assert len(MapPackage(tmp_path / "c")) == len(corridor_tiles(naip_map, route, 1200.0))
    again = runner.invoke(app, [*args, "--width", "1.2km"])
    assert isinstance(again.exception, OrthonavError) and "exists" in str(again.exception)
    bad = runner.invoke(app, [*args, "--width", "wide", "--overwrite"])
    assert isinstance(bad.exception, OrthonavError) and "--width" in str(bad.exception)
