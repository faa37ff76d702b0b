"""Positions off the map: ``map info`` shows where the map is, every error about a position off it
says where that position and the map are, and a batch whose every prior misses the map says so
after its summary and exits 2, as replay does."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import TERRAIN
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.geo import distance_m
from orthonav.mapdb import MapPackage

runner = CliRunner()
FAR = (10.0, 10.0)  # thousands of km from the synthetic map


def latlon(text: str) -> tuple[float, float]:
    lat, lon = (float(v) for v in text.split(","))
    return lat, lon


def test_map_info_shows_the_corners_and_the_size(terrain_map: MapPackage) -> None:
    result = runner.invoke(app, ["map", "info", str(terrain_map.path), "--json"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.output)
    (south, west), (north, east) = latlon(info["south_west_latlon"]), latlon(info["north_east_latlon"])
    lat, lon = latlon(info["centre_latlon"])
    assert south < lat < north and west < lon < east
    side_m = TERRAIN.size_px * TERRAIN.gsd_m
    # The corners bound the map (a UTM grid is turned against the meridians: a little more).
    assert side_m <= float(distance_m(south, west, south, east)) < 1.05 * side_m
    assert side_m <= float(distance_m(south, west, north, west)) < 1.05 * side_m
    assert info["size_m"] == f"{side_m:.0f} x {side_m:.0f} m"


@pytest.fixture(scope="module")
def frame_dir(terrain_map: MapPackage, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three frames of the map camera's size (their content does not matter off the map)."""
    folder = tmp_path_factory.mktemp("frames")
    camera = terrain_map.camera
    for i in range(3):
        cv2.imwrite(str(folder / f"f{i}.png"), np.full((camera.height, camera.width, 3), 90 + i, np.uint8))
    return folder


def test_a_prior_off_the_map_is_told_with_the_maps_extent(terrain_map: MapPackage, frame_dir: Path) -> None:
    result = runner.invoke(
        app, ["localize", str(terrain_map.path), str(frame_dir / "f0.png"), "--prior", f"{FAR[0]},{FAR[1]}"]
    )
    assert isinstance(result.exception, OrthonavError), result.output
    message = str(result.exception)
    summary = terrain_map.summary()
    for fragment in ("km from the map's centre", summary["south_west_latlon"], summary["north_east_latlon"]):
        assert fragment in message, (fragment, message)
    assert summary["size_m"] in message


def test_a_batch_with_every_prior_off_the_map_prints_its_summary_and_exits_2(
    terrain_map: MapPackage, frame_dir: Path, tmp_path: Path
) -> None:
    priors = tmp_path / "priors.csv"
    priors.write_text("name,lat,lon\n" + "".join(f"f{i}.png,{FAR[0]},{FAR[1]}\n" for i in range(3)))
    result = runner.invoke(app, ["localize", str(terrain_map.path), str(frame_dir), "--priors", str(priors)])
    assert isinstance(result.exception, OrthonavError), result.output
    assert "localize: 0 of 3 frames fixed" in result.output
    message = str(result.exception)
    assert message.startswith(f"none of the 3 frames' prior positions is on the map {terrain_map.path}")
    away_km = float(distance_m(*terrain_map.grid.center_latlon, *FAR)) / 1000.0
    assert f"{away_km:.1f} km from the map's centre" in message
    assert terrain_map.summary()["north_east_latlon"] in message


def test_a_batch_with_one_prior_on_the_map_is_not_an_error(
    terrain_map: MapPackage, frame_dir: Path, tmp_path: Path
) -> None:
    """Frames off the map beside one on it are rejected rows of an ordinary run."""
    lat, lon = terrain_map.grid.center_latlon
    priors = tmp_path / "priors.csv"
    priors.write_text(
        f"name,lat,lon\nf0.png,{lat},{lon}\nf1.png,{FAR[0]},{FAR[1]}\nf2.png,{FAR[0]},{FAR[1]}\n"
    )
    result = runner.invoke(app, ["localize", str(terrain_map.path), str(frame_dir), "--priors", str(priors)])
    assert result.exit_code == 0, result.output
    assert "of 3 frames fixed" in result.output
