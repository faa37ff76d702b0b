"""The ``orthonav`` command line: map build/info, localize (single and batch), simulate, demo, errors."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import TERRAIN, TERRAIN_ALT_M, noisy_prior, png_declaring, random_pose, zeroed_middle
from pyproj import CRS
from pyproj.aoi import AreaOfInterest
from pyproj.database import query_utm_crs_info
from typer.testing import CliRunner

from orthonav.camera import Camera
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.mapdb import MapPackage

runner = CliRunner()

FIX_KEYS = {
    "name",
    "lat",
    "lon",
    "heading",
    "altitude",
    "accepted",
    "reason",
    "inliers",
    "rmse",
    "covariance",
    "timings",
}


def invoke(*args: str | Path):
    return runner.invoke(app, [str(a) for a in args])


def expect_error(result, *fragments: str) -> str:
    """The command failed with an OrthonavError whose message names every fragment."""
    assert isinstance(result.exception, OrthonavError), (result.exception, result.output)
    message = str(result.exception)
    for fragment in fragments:
        assert fragment in message, (fragment, message)
    return message


@pytest.fixture(scope="module")
def frames(terrain_raster: GeoRaster, camera: Camera, tmp_path_factory: pytest.TempPathFactory):
    """Three PNG frames at known poses, with a priors CSV and a camera JSON; returns (dir, poses)."""
    rng = np.random.default_rng(17)
    folder = tmp_path_factory.mktemp("frames")
    poses: dict[str, TruePose] = {}
    rows = []
    for i in range(3):
        pose = random_pose(rng, terrain_raster, camera, TERRAIN_ALT_M)
        name = f"frame_{i:02d}.png"
        assert cv2.imwrite(
            str(folder / name), render_frame(terrain_raster, camera, pose, Photometric.random(rng), rng)
        )
        p = noisy_prior(rng, pose).prior
        rows.append([name, p.lat, p.lon, p.alt_agl_m, p.heading_deg, p.pitch_deg, p.roll_deg, ""])
        poses[name] = pose
    with open(folder.parent / "priors.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["name", "lat", "lon", "altitude", "heading", "pitch", "roll", "sigma_m"])
        writer.writerows(rows)
    (folder.parent / "camera.json").write_text(json.dumps({"width": 640, "height": 480, "hfov_deg": 60}))
    return folder, poses


# --- map build / info ---------------------------------------------------------------------


def test_map_build_then_info_json(terrain_tif: Path, tmp_path: Path) -> None:
    out = tmp_path / "map"
    result = invoke("map", "build", terrain_tif, "--out", out, "--altitude", "300", "--max-keypoints", "500")
    assert result.exit_code == 0, result.output
    assert (out / "manifest.json").is_file()

    result = invoke("map", "info", out, "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert Path(info["source"]) == terrain_tif.resolve()
    # The terrain is written in the UTM zone of its centre: ask the PROJ database which one that is.
    utm = query_utm_crs_info(
        datum_name="WGS 84",
        area_of_interest=AreaOfInterest(
            TERRAIN.center_lon, TERRAIN.center_lat, TERRAIN.center_lon, TERRAIN.center_lat
        ),
    )
    assert CRS.from_user_input(info["crs"]) == CRS.from_epsg(int(utm[0].code))
    # At 300 m the camera sees 0.54 m/px, finer than the map: the map's 1 m/px is the work resolution.
    assert info["work_gsd_m"] == pytest.approx(TERRAIN.gsd_m, rel=1e-3)
    assert info["area_km2"] == pytest.approx((TERRAIN.size_px * TERRAIN.gsd_m / 1000) ** 2, rel=1e-3)
    assert info["nominal_alt_m"] == 300.0
    assert 0 < info["keypoints"] <= 500 * int(info["tiles"].split()[0])
    lat, lon = (float(v) for v in info["centre_latlon"].split(","))
    assert float(distance_m(lat, lon, TERRAIN.center_lat, TERRAIN.center_lon)) < 2.0


def test_map_build_refuses_to_overwrite(terrain_map: MapPackage, terrain_tif: Path) -> None:
    result = invoke("map", "build", terrain_tif, "--out", terrain_map.path)
    expect_error(result, str(terrain_map.path), "already exists", "--overwrite")


def test_map_verify_then_fly_refuses_a_damaged_package(terrain_map: MapPackage, tmp_path: Path) -> None:
    """One bit flipped in a feature chunk: `map verify` exits 2 naming the chunk and its area, and
    `fly` refuses to start on it (before opening any link); the intact package verifies."""
    result = invoke("map", "verify", terrain_map.path)
    assert result.exit_code == 0, result.output
    assert f"map {terrain_map.path}: intact ({len(terrain_map)} tiles" in result.output
    copy = tmp_path / "copy.map"
    shutil.copytree(terrain_map.path, copy)
    chunk = sorted((copy / "features").glob("chunk_*.npy"))[-1]
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x01
    chunk.write_bytes(bytes(data))
    expect_error(invoke("map", "verify", copy), f"{chunk} checksum mismatch (tiles ", "lat ", "lon ")
    fly = ["fly", "--map", copy, "--frames", tmp_path, "--connect", "udpin:127.0.0.1:1", "--duration", "1"]
    expect_error(invoke(*fly), "map package damaged", f"{chunk} checksum mismatch")


def test_fly_warns_of_a_camera_fixed_to_the_body_and_not_of_a_gimbal(tmp_path: Path) -> None:
    fly = [
        "fly",
        "--map",
        tmp_path,
        "--frames",
        tmp_path,
        "--connect",
        "udpin:127.0.0.1:1",
        "--duration",
        "1",
    ]
    body = invoke(*fly)
    expect_error(body, "not a map package")
    assert "fixed to the body (no --nadir-gimbal)" in body.output
    gimbal = invoke(*fly, "--nadir-gimbal")
    expect_error(gimbal, "not a map package")
    assert "fixed to the body" not in gimbal.output


def test_map_info_of_a_non_map(tmp_path: Path) -> None:
    expect_error(invoke("map", "info", tmp_path), str(tmp_path), "not a map package")


# --- localize -----------------------------------------------------------------------------


def test_localize_one_frame_json(terrain_map: MapPackage, frames) -> None:
    """One frame + command-line prior -> one JSON object on stdout, at the true position."""
    folder, poses = frames
    name = "frame_00.png"
    pose = poses[name]
    result = invoke(
        "localize",
        terrain_map.path,
        folder / name,
        "--prior", f"{pose.lat + 0.001},{pose.lon}",
        "--altitude", pose.alt_agl_m,
        "--heading", (pose.yaw_deg + 5) % 360,
        "--pitch", pose.pitch_deg,
        "--roll", pose.roll_deg,
        "--json",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    lines = result.stdout.strip().splitlines()
    assert len(lines) == 1
    record = json.loads(lines[0])
    assert set(record) >= FIX_KEYS
    assert record["name"] == name
    assert record["accepted"] is True and record["reason"] == ""
    assert float(distance_m(pose.lat, pose.lon, record["lat"], record["lon"])) < 3.0  # exact attitude prior
    assert abs((record["heading"] - pose.yaw_deg + 180) % 360 - 180) < 1.0
    assert record["altitude"] == pytest.approx(pose.alt_agl_m, rel=0.03)
    cov = np.array(record["covariance"])
    assert cov.shape == (2, 2) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert record["inliers"] >= 20 and record["rmse"] > 0
    assert record["timings"]["total_ms"] > 0


def test_localize_batch_with_priors_camera_and_out(terrain_map: MapPackage, frames, tmp_path: Path) -> None:
    """A folder of frames (one undecodable) -> one JSON line per frame; the broken one is a rejection."""
    folder, poses = frames
    batch = tmp_path / "frames"
    shutil.copytree(folder, batch)
    (batch / "broken.jpg").write_bytes(b"\x00\x01 not an image" * 50)
    (batch / "notes.txt").write_text("not a frame: ignored")
    shutil.copy(next(folder.glob("*.png")), batch / "matches_00001.png")  # a mission's picture, not a frame
    out = tmp_path / "fixes.jsonl"
    plot = tmp_path / "fixes.png"

    result = invoke(
        "localize", terrain_map.path, batch, "--priors", folder.parent / "priors.csv",
        "--camera", folder.parent / "camera.json", "--out", out, "--plot", plot,
    )  # fmt: skip

    assert result.exit_code == 0, result.output
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert sorted(r["name"] for r in records) == sorted([*poses, "broken.jpg"])
    fixed = sum(r["accepted"] for r in records)
    assert f"localize: {fixed} of {len(records)} frames fixed" in result.output
    for r in records:
        if r["name"] == "broken.jpg":
            assert r["accepted"] is False and "cannot be decoded" in r["reason"]
        else:
            pose = poses[r["name"]]
            assert r["accepted"] is True, r["reason"]
            # attitude prior 0.3 deg off at <= 360 m: h tan(e) is a few metres
            assert float(distance_m(pose.lat, pose.lon, r["lat"], r["lon"])) < 8.0


def test_localize_batch_frame_of_the_wrong_size_is_a_rejected_record(
    terrain_map: MapPackage, tmp_path: Path
) -> None:
    folder = tmp_path / "frames"
    folder.mkdir()
    cv2.imwrite(str(folder / "small.png"), np.zeros((240, 320, 3), np.uint8))
    result = invoke("localize", terrain_map.path, folder, "--json")
    assert result.exit_code == 0, result.output
    record = json.loads(result.stdout)
    assert record["accepted"] is False and "320x240" in record["reason"] and "640x480" in record["reason"]


def test_localize_batch_damaged_and_oversized_frames_are_rejected_records(
    terrain_map: MapPackage, frames, tmp_path: Path
) -> None:
    """A JPEG with zeroed data and a PNG over OpenCV's pixel limit are each one rejected row with
    its reason; the frames after them are still localized."""
    folder, _ = frames
    batch = tmp_path / "frames"
    batch.mkdir()
    ok, data = cv2.imencode(".jpg", cv2.imread(str(folder / "frame_00.png")))
    assert ok
    (batch / "a_zeroed.jpg").write_bytes(zeroed_middle(data.tobytes()))
    (batch / "b_huge.png").write_bytes(png_declaring(40000, 40000))
    shutil.copy(folder / "frame_00.png", batch / "c_good.png")
    result = invoke("localize", terrain_map.path, batch, "--json")
    assert result.exit_code == 0, result.output
    records = {r["name"]: r for r in map(json.loads, result.stdout.splitlines())}
    assert list(records) == ["a_zeroed.jpg", "b_huge.png", "c_good.png"]
    assert not records["a_zeroed.jpg"]["accepted"]
    assert "damaged JPEG (Corrupt JPEG data" in records["a_zeroed.jpg"]["reason"]
    assert not records["b_huge.png"]["accepted"]
    assert "CV_IO_MAX_IMAGE_PIXELS" in records["b_huge.png"]["reason"]
    assert "damaged" not in records["c_good.png"]["reason"]


def test_localize_single_missing_frame_is_an_error(terrain_map: MapPackage, tmp_path: Path) -> None:
    expect_error(invoke("localize", terrain_map.path, tmp_path / "none.jpg"), "none.jpg", "no such frame")


def test_localize_empty_folder_is_an_error(terrain_map: MapPackage, tmp_path: Path) -> None:
    expect_error(invoke("localize", terrain_map.path, tmp_path), str(tmp_path), "no image files")


PRIOR_HEADER = "name,lat,lon,altitude,heading,pitch,roll,sigma_m\n"


@pytest.mark.parametrize(
    ("rows", "fragments"),
    [
        (
            "frame_00.png,50.45,30.52,300,0,,,\nframe_01.png,50.45,30.52,high,0,,,\n",
            [":3", "'altitude'", "'high'"],
        ),
        ("frame_00.png,50.45,30.52,nan,0,,,\n", [":2", "'altitude'", "finite"]),
        ("frame_00.png,50.45,30.52,300,inf,,,\n", [":2", "'heading'", "finite"]),
        ("frame_00.png,95,30.52,300,0,,,\n", [":2", "latitude 95"]),
        ("frame_00.png,50.45,,300,0,,,\n", [":2", "latitude and longitude"]),
        ("frame_00.png,50.45,30.52,300,0,,,0\n", [":2", "sigma_m"]),
        ("frame_00.png,50.45,30.52,300,0,3,,\n", [":2", "pitch and roll"]),
    ],
    ids=["non-numeric", "nan", "inf", "lat95", "lat-only", "sigma0", "pitch-only"],
)
def test_priors_csv_errors_name_file_line_and_field(
    terrain_map: MapPackage, frames, tmp_path: Path, rows: str, fragments: list[str]
) -> None:
    folder, _ = frames
    priors = tmp_path / "priors.csv"
    priors.write_text(PRIOR_HEADER + rows)
    result = invoke("localize", terrain_map.path, folder, "--priors", priors)
    message = expect_error(result, str(priors), *fragments)
    assert f"{priors}:" in message


def test_priors_csv_without_name_column(terrain_map: MapPackage, frames, tmp_path: Path) -> None:
    folder, _ = frames
    priors = tmp_path / "priors.csv"
    priors.write_text("file,lat,lon\nframe_00.png,50.45,30.52\n")
    expect_error(invoke("localize", terrain_map.path, folder, "--priors", priors), str(priors), "'name'")


@pytest.mark.parametrize(
    ("camera_data", "fragment"),
    [
        ({"width": 640, "height": 480, "hfov_deg": 0}, "hfov_deg"),
        ({"width": 640, "height": 480, "hfov_deg": 180}, "hfov_deg"),
        ({"width": 640, "height": 480, "fx": -500, "fy": 500, "cx": 320, "cy": 240}, "fx"),
        ({"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 900, "cy": 240}, "cx"),
        ({"width": 640, "height": 480}, "missing field"),
        ({"width": "wide", "height": 480, "hfov_deg": 60}, "expected a finite number"),
    ],
)
def test_camera_json_with_impossible_values(
    terrain_map: MapPackage, frames, tmp_path: Path, camera_data: dict, fragment: str
) -> None:
    folder, _ = frames
    path = tmp_path / "camera.json"
    path.write_text(json.dumps(camera_data))
    expect_error(invoke("localize", terrain_map.path, folder, "--camera", path), str(path), fragment)


def test_camera_json_that_is_not_json(terrain_map: MapPackage, frames, tmp_path: Path) -> None:
    folder, _ = frames
    path = tmp_path / "camera.json"
    path.write_text("{width: 640")
    expect_error(invoke("localize", terrain_map.path, folder, "--camera", path), str(path), "not valid JSON")


# --- simulate and demo --------------------------------------------------------------------


def _latlon(package: MapPackage, fx: float, fy: float) -> str:
    lat, lon = package.grid.pixel_to_latlon(fx * package.grid.width, fy * package.grid.height)
    return f"{float(lat):.6f},{float(lon):.6f}"


def test_simulate_writes_the_run_outputs(terrain_map: MapPackage, tmp_path: Path) -> None:
    out = tmp_path / "run"
    result = invoke(
        "simulate", terrain_map.path, "--start", _latlon(terrain_map, 0.3, 0.3),
        "--target", _latlon(terrain_map, 0.7, 0.75), "--out", out, "--seed", "2", "--arrival-radius", "40",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    for name in ("steps.jsonl", "summary.json", "config.json", "trajectory.png"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "summary.json").read_text())
    assert summary["arrived"] is True
    steps = (out / "steps.jsonl").read_text().splitlines()
    assert len(steps) == summary["steps"]
    config = json.loads((out / "config.json").read_text())
    assert config["mission"]["seed"] == 2 and config["mission"]["arrival_radius_m"] == 40.0


@pytest.mark.parametrize(
    ("start", "fragment"),
    [
        ("50.45", "expected LAT,LON"),
        ("north,east", "expected LAT,LON"),
        ("1,2,3", "expected LAT,LON"),
        ("95,30", "latitude 95"),
    ],
)
def test_simulate_malformed_start(terrain_map: MapPackage, tmp_path: Path, start: str, fragment: str) -> None:
    result = invoke(
        "simulate",
        terrain_map.path,
        "--start",
        start,
        "--target",
        _latlon(terrain_map, 0.7, 0.7),
        "--out",
        tmp_path / "r",
    )
    expect_error(result, "--start", fragment)
    assert not (tmp_path / "r").exists()


def test_simulate_start_outside_the_map(terrain_map: MapPackage, tmp_path: Path) -> None:
    result = invoke(
        "simulate",
        terrain_map.path,
        "--start",
        "10,10",
        "--target",
        _latlon(terrain_map, 0.7, 0.7),
        "--out",
        tmp_path / "r",
    )
    expect_error(result, "mission start", "outside the map")


def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    result = invoke("demo", "--out", out, "--seed", "1")
    assert result.exit_code == 0, result.output
    for rel in ("terrain.tif", "map/manifest.json", "run/steps.jsonl", "run/summary.json", "run/config.json"):
        assert (out / rel).is_file(), rel
    assert (out / "run" / "trajectory.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads((out / "run" / "summary.json").read_text())
    print(f"\ndemo summary: {summary}")
    assert summary["steps"] == len((out / "run" / "steps.jsonl").read_text().splitlines())
    assert summary["arrived"] is True
    # The fix source `orthonav fly` uses by default.
    assert json.loads((out / "run" / "config.json").read_text())["fix_source"] == "cascade:orb"


# --- the installed console script ---------------------------------------------------------


def test_console_script_turns_user_errors_into_one_line_and_exit_code_2(tmp_path: Path) -> None:
    """A user error is one 'error: ...' line on stderr (even in a narrow terminal), exit 2, no traceback."""
    exe = shutil.which("orthonav")
    if exe is None:
        pytest.skip("the orthonav console script is not on PATH (pip install -e .)")
    missing = tmp_path / ("a_rather_long_directory_name_" * 3) / "[red]map"
    env = {**os.environ, "COLUMNS": "40", "NO_COLOR": "1"}
    proc = subprocess.run(
        [exe, "localize", str(missing), str(tmp_path / "frame.jpg")],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    assert str(missing) in lines[0]  # the path, brackets and all: not eaten as markup
    assert proc.stdout == ""


def test_localize_a_folder_by_dense_correlation(terrain_map: MapPackage, frames, tmp_path: Path) -> None:
    """``--fix-source correlation`` runs the dense corrector over a folder with the same priors and
    outputs; its fixes land where the frames were taken."""
    folder, poses = frames
    out = tmp_path / "fixes.jsonl"
    result = invoke(
        "localize", terrain_map.path, folder, "--priors", folder.parent / "priors.csv",
        "--fix-source", "correlation", "--out", out,
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == len(poses) and all(r["method"].startswith("correction:") for r in records)
    fixed = [r for r in records if r["accepted"]]
    assert fixed, [r["reason"] for r in records]
    for r in fixed:
        assert float(distance_m(poses[r["name"]].lat, poses[r["name"]].lon, r["lat"], r["lon"])) < 15.0
    expect_error(
        invoke("localize", terrain_map.path, folder, "--fix-source", "sift"), "--fix-source", "correlation"
    )


def test_localize_a_folder_with_the_cascade(naip_map: MapPackage, camera: Camera, tmp_path: Path) -> None:
    """``--fix-source cascade`` runs over a folder with the same priors and outputs as the others."""
    from conftest import NAIP_ALT_M

    rng = np.random.default_rng(3)
    folder = tmp_path / "frames"
    folder.mkdir()
    rows, poses = [], {}
    with GeoRaster(naip_map.source_path) as raster:
        for i in range(2):
            pose = random_pose(rng, raster, camera, NAIP_ALT_M)
            name = f"f{i}.png"
            cv2.imwrite(str(folder / name), render_frame(raster, camera, pose, Photometric(), rng))
            p = noisy_prior(rng, pose).prior
            rows.append([name, p.lat, p.lon, p.alt_agl_m, p.heading_deg, p.pitch_deg, p.roll_deg, 100])
            poses[name] = pose
    with open(tmp_path / "priors.csv", "w", newline="") as fh:
        header = ["name", "lat", "lon", "altitude", "heading", "pitch", "roll", "sigma_m"]
        csv.writer(fh).writerows([header, *rows])
    out = tmp_path / "fixes.jsonl"
    priors = tmp_path / "priors.csv"
    result = invoke(
        "localize", naip_map.path, folder, "--priors", priors, "--fix-source", "cascade", "--out", out
    )
    assert result.exit_code == 0, result.output
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == 2 and all("p_correct" in r["quality"] for r in records)
    assert any(r["accepted"] for r in records), [r["reason"] for r in records]
    for r in (r for r in records if r["accepted"]):
        assert float(distance_m(poses[r["name"]].lat, poses[r["name"]].lon, r["lat"], r["lon"])) < 25.0


def test_localize_with_a_fallback_map(terrain_map: MapPackage, frames, tmp_path: Path) -> None:
    """``--fallback MAP`` puts another map's fix source behind the first: a frame the first fixes
    is its fix; one both reject names each one's reason. Correlation has no map features to fall
    back on, and a fallback that is not a map package is named."""
    folder, poses = frames
    out = tmp_path / "fixes.jsonl"
    priors = folder.parent / "priors.csv"
    result = invoke(
        "localize", terrain_map.path, folder, "--priors", priors, "--fallback", terrain_map.path,
        "--out", out, "--fix-source", "keypoints",
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "fix source: keypoints (orb, then orb-2 where the one before rejects)" in result.output
    records = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(records) == len(poses)
    backend = terrain_map.backend_name
    for r in records:
        if r["accepted"]:
            assert r["method"] in (backend, f"{backend} (fallback 2 of 2)")
            assert r["quality"]["fallback_stage"] in (0, 1) and f"{backend}_ms" in r["timings"]
        else:
            assert r["reason"].startswith(f"{backend}: ") and f"; {backend}-2: " in r["reason"]
    assert any(r["accepted"] for r in records)
    expect_error(
        invoke(
            "localize",
            terrain_map.path,
            folder,
            "--fix-source",
            "correlation",
            "--fallback",
            terrain_map.path,
        ),
        "fallback maps",
        "correlation",
    )
    expect_error(invoke("localize", terrain_map.path, folder, "--fallback", tmp_path / "nomap"), "nomap")
