"""The mission benchmark on the real NAIP map, cut down to two missions and a short companion run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import CAMERA, naip_path
from typer.testing import CliRunner

from orthonav.bench.mission import INS_ONLY, MissionBenchConfig, companion_latency, run_mission_benchmark
from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, distance_m
from orthonav.mapdb import MapPackage

pytest.importorskip("pymavlink", reason="the companion latency needs the 'mavlink' extra")


@pytest.fixture(scope="module")
def bench(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, Path]:
    """Same-date frames (map and frames from 2020), so ORB fixes and the missions can arrive."""
    out = tmp_path_factory.mktemp("bench_mission") / "bench.json"
    config = MissionBenchConfig(missions=2, features=("orb",), latency_s=6.0)
    tif = naip_path("20200831")
    return run_mission_benchmark(tif, tif, out, config, progress=False), out


def test_every_mission_is_flown_by_the_backend_and_by_the_ins_alone(bench) -> None:
    result, out = bench
    rows = result["rows"]
    assert [(r["features"], r["mission"]) for r in rows] == [
        ("orb", 0),
        ("orb", 1),
        (INS_ONLY, 0),
        (INS_ONLY, 1),
    ]
    for i in range(2):
        configs = [
            json.loads((Path(r["run_dir"]) / "config.json").read_text())["mission"]
            for r in rows
            if r["mission"] == i
        ]
        assert configs[0]["start_lat"] == configs[1]["start_lat"] and configs[0]["seed"] == configs[1]["seed"]
        assert configs[0]["visual_fixes"] and not configs[1]["visual_fixes"]
    assert json.loads(out.read_text())["config"]["missions"] == 2
    assert out.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_arrival_is_judged_by_the_true_distance(bench) -> None:
    result, _ = bench
    for row in result["rows"]:
        summary = json.loads((Path(row["run_dir"]) / "summary.json").read_text())
        steps = [json.loads(line) for line in (Path(row["run_dir"]) / "nav.jsonl").read_text().splitlines()]
        config = json.loads((Path(row["run_dir"]) / "config.json").read_text())["mission"]
        last = steps[-1]
        true_left = float(
            distance_m(last["true_lat"], last["true_lon"], config["target_lat"], config["target_lon"])
        )
        # The last 1 Hz record lies at most one second of flight before the end.
        assert abs(true_left - summary["true_distance_to_target_m"]) <= config["speed_mps"] + 1.0
        assert row["arrived_true"] == (row["true_distance_to_target_m"] <= config["arrival_radius_m"])
    orb, ins = result["summary"]["orb"], result["summary"][INS_ONLY]
    print(f"\norb: {orb}\nINS alone: {ins}")
    assert orb["arrived_true"] == 1.0 and orb["nav_error_mean_m"] < 25.0 and orb["fix_rate"] >= 0.8
    assert ins["fix_rate"] == 0.0 and ins["nav_error_mean_m"] > orb["nav_error_mean_m"]


def test_companion_latency_is_measured_over_udp(bench) -> None:
    result, _ = bench
    (latency,) = result["latency"]
    assert latency["features"] == "orb" and latency["fused"] >= 3 and latency["sent"] >= 10
    assert 0 < latency["latency_median_ms"] <= latency["latency_p95_ms"] < 5000
    assert 0 <= latency["wait_median_ms"] <= latency["wait_p95_ms"] <= latency["latency_p95_ms"]
    assert latency["gps_input_error_median_m"] < 15.0


def test_the_loop_can_fly_another_dates_frames(bench, naip_map: MapPackage, naip_raster: GeoRaster) -> None:
    """The loop's camera over 2009 imagery, the map of 2020 (``bench speed --latency-frames
    cross-date``): ORB's keypoints, which fused the map's own frames in the loop above, fuse none
    or almost none of these; the loop still runs its frames through."""
    from orthonav.localize import KEYPOINTS, make_fix_source
    from orthonav.sim import SIMULATED_WORLD

    result, _ = bench
    (same_date,) = result["latency"]
    config = MissionBenchConfig(missions=1, features=("orb",), latency_s=6.0)
    source = make_fix_source(KEYPOINTS, naip_map, CAMERA, naip_raster, SIMULATED_WORLD)
    with GeoRaster(naip_path("20090818")) as frames_from:
        other = companion_latency(naip_map, source, naip_raster, CAMERA, "orb_2009", config, frames_from)
    print(f"\nthe map's own frames: {same_date}\n2009's: {other}")
    assert other["frames"] >= 8 and other["fused"] <= 1 < same_date["fused"]


def test_cli_prints_the_tables_and_names_bad_dates(tmp_path: Path) -> None:
    data = tmp_path / "naip"
    data.mkdir()
    for year in ("20180716", "20200831"):
        (data / naip_path(year).name).symlink_to(naip_path(year))
    runner = CliRunner()
    args = ["bench", "mission", "--data", str(data), "--missions", "1", "--latency-s", "0"]
    result = runner.invoke(app, [*args, "--map-date", "2020", "--out", str(tmp_path / "b.json")])
    assert result.exit_code == 0, result.output
    assert "ins-only" in result.output and "arrived true" in result.output  # headers split at "_"
    result = runner.invoke(app, [*args, "--map-date", "20"])
    assert isinstance(result.exception, OrthonavError) and "exactly one" in str(result.exception)
    with pytest.raises(OrthonavError, match="missions"):
        MissionBenchConfig(missions=0)


def test_the_cascade_flies_across_dates_where_keypoints_alone_do_not(tmp_path: Path) -> None:
    """Map 2018, frames 2020: the cascade (correlation, then keypoints, verification, acceptance)
    as a mission's fix source and in companion mode, side by side with ORB alone."""
    config = MissionBenchConfig(missions=1, features=("cascade", "orb"), latency_s=6.0)
    result = run_mission_benchmark(
        naip_path("20180716"), naip_path("20200831"), tmp_path / "b.json", config, progress=False
    )
    cascade, orb = result["summary"]["cascade"], result["summary"]["orb"]
    print(f"\ncascade: {cascade}\norb: {orb}")
    assert cascade["fix_rate"] >= 0.6 and cascade["fix_rate"] > orb["fix_rate"]
    assert cascade["nav_error_mean_m"] < orb["nav_error_mean_m"]
    latency = next(row for row in result["latency"] if row["features"] == "cascade")
    assert latency["fused"] >= 3 and 0 < latency["latency_median_ms"] <= latency["latency_p95_ms"] < 5000
