"""``orthonav replay companion.jsonl``: the navigation filter re-run offline on a real companion log.

The log comes from a real loop: the simulated vehicle over the NAIP 2020 orthophoto and the
companion (``fly``) over UDP loopback, GNSS healthy for the first seconds. The vehicle does not
stream GPS_RAW_INT, so the log is given one per GLOBAL_POSITION_INT (3-D fix while GNSS worked,
none after), as an ArduPilot log would have it, and its start record says the companion flew
without the seed those would have given it.
"""

from __future__ import annotations

import itertools
import json
import logging
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from conftest import CAMERA, NAIP_ALT_M
from typer.testing import CliRunner

from orthonav.cli.main import app
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster, destination
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage
from orthonav.mavlink.companion import CompanionConfig
from orthonav.mavlink.link import dialect
from orthonav.replay import read_companion_log, replay_companion_log, settings_from_log
from orthonav.types import Fix, Pose
from orthonav.vehicle.loopback import fly_loopback
from orthonav.vehicle.simulated import SimVehicleConfig

GNSS_S = 6.0  # the vehicle's GNSS works this long, then its INS drifts
RUN_S = 12.0


@pytest.fixture(scope="module")
def companion_log(naip_map: MapPackage, naip_raster: GeoRaster, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("replay_companion")
    lat, lon = naip_raster.center_latlon
    vehicle = SimVehicleConfig(
        *destination(lat, lon, 270.0, 500.0),
        *destination(lat, lon, 90.0, 1000.0),
        speed_mps=20.0,
        alt_agl_m=NAIP_ALT_M,
        frame_rate_hz=2.0,
        gnss_loss_s=GNSS_S,
    )
    _, summary = fly_loopback(
        Localizer(naip_map, CAMERA), naip_raster, CAMERA, vehicle, CompanionConfig(duration_s=RUN_S), root
    )
    assert summary["fused"] >= 3 and summary["sent"] >= 20
    path = root / "companion" / "companion.jsonl"
    return with_gps_raw(path, root / "companion_gnss.jsonl")


def with_gps_raw(path: Path, out: Path) -> Path:
    """A GPS_RAW_INT before every GLOBAL_POSITION_INT of the same pass: 3-D fix while GNSS worked."""
    mavlink = dialect()
    lines, first = [], None
    for line in path.read_text().splitlines():
        record = json.loads(line)
        if record["kind"] == "start":  # it heard no GPS_RAW_INT: nothing seeded its filter
            line = json.dumps({**record, "config": {**record["config"], "gnss_seed": False}})
        if record["kind"] == "recv" and record["type"] == "GLOBAL_POSITION_INT":
            first = first or record["time_s"]
            fix_type = 3 if record["time_s"] - first < GNSS_S - 1.0 else 1
            pos = record["msg"]
            raw = mavlink.MAVLink_gps_raw_int_message(
                0, fix_type, pos["lat"], pos["lon"], pos["alt"], 90, 90, 0, 0, 12
            )
            lines.append(json.dumps({**record, "type": "GPS_RAW_INT", "msg": raw.to_dict()}))
        lines.append(line)
    out.write_text("\n".join(lines) + "\n")
    return out


def expect_error(result, fragment: str) -> None:
    assert isinstance(result.exception, OrthonavError), (result.exception, result.output)
    assert fragment in str(result.exception)


def records(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def replay(path: Path, out: Path, **overrides):
    log = read_companion_log(path)
    return replay_companion_log(log, settings_from_log(log.config, overrides), out, overrides)


def test_the_rerun_with_the_companions_settings_reproduces_what_it_sent(
    companion_log: Path, tmp_path: Path
) -> None:
    result = replay(companion_log, tmp_path)
    summary = result.summary
    print(json.dumps(summary, indent=1))
    sent = sum(r["kind"] == "sent" for r in records(companion_log))
    vs_sent = summary["vs_sent"]
    assert vs_sent["states"] == sent and vs_sent["would_send"] == sent
    assert vs_sent["position_offset_m"]["max"] < 0.05 and vs_sent["sigma_difference_m_max"] < 0.05
    assert vs_sent["status_differs"] == 0
    fixes = summary["fixes"]
    assert fixes["verdicts_changed"] == 0 and fixes["fused"] == fixes["originally_fused"] >= 3
    assert summary["skipped_lines"] == {}
    # The GNSS reference: only while GPS_RAW_INT reported a 3-D fix.
    reference = summary["gnss_reference"]
    assert reference["points"] >= 20 and reference["span_s"] < GNSS_S
    assert reference["rerun_error_m"]["median"] < 15.0 and reference["sent_error_m"]["median"] < 15.0
    # Outputs: 1 Hz states, the picture, the settings.
    nav = records(tmp_path / "nav.jsonl")
    assert len(nav) >= RUN_S - 3 and np.all(np.diff([r["time_s"] for r in nav]) >= 0.999)
    assert any(r["gnss_error_m"] is not None for r in nav) and any(r["gnss_error_m"] is None for r in nav)
    assert (tmp_path / "replay.png").stat().st_size > 20_000
    config = json.loads((tmp_path / "config.json").read_text())
    assert config["settings"]["imu"] == "consumer" and config["companion"]["duration_s"] == RUN_S
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # atomic writes, no leftovers


def test_filter_options_change_the_rerun_from_the_command_line(companion_log: Path, tmp_path: Path) -> None:
    out = tmp_path / "tuned"
    args = ["replay", str(companion_log), "--imu", "tactical", "--gate-probability", "0.99"]
    result = CliRunner().invoke(
        app, [*args, "--max-sigma", "1", "--heading-fix-sigma", "none", "--out", str(out)]
    )
    assert result.exit_code == 0, (result.exception, result.output)
    assert "fixes fused" in result.output and "re-run vs sent" in result.output
    summary = json.loads((out / "summary.json").read_text())
    settings = summary["settings"]
    assert (settings["imu"], settings["gate_probability"], settings["max_sigma_m"]) == ("tactical", 0.99, 1.0)
    assert settings["heading_fix_sigma_deg"] is None and settings["init_sigma_m"] == 100.0
    assert summary["vs_sent"]["would_send"] < summary["vs_sent"]["states"]  # 1 m is stricter than 50 m
    assert summary["time_s"]["not sent (untrusted)"] > 0.0
    assert json.loads((out / "config.json").read_text())["overrides"]["imu"] == "tactical"
    bad = CliRunner().invoke(app, ["replay", str(companion_log), "--imu", "mems", "--out", str(out)])
    expect_error(bad, "IMU preset 'mems'")
    mixed = CliRunner().invoke(app, ["replay", str(companion_log), "--map", str(tmp_path), "--out", str(out)])
    expect_error(mixed, "--map: a companion log re-runs the navigation filter")
    photos = CliRunner().invoke(app, ["replay", str(tmp_path), "--imu", "tactical"])
    expect_error(photos, "--imu: filter options apply to a companion log")


def test_the_rerun_withholds_states_past_the_reckoning_limit_as_fly_does(
    companion_log: Path, tmp_path: Path
) -> None:
    """A limit inside the flight's own ages of the last fix (how late fixes come depends on how busy
    the machine was), halfway between two of them that split the states most evenly (a busy
    machine's fixes can leave half the states at one age): the states past it are withheld, the
    others still go."""
    ages = [row["since_fix_s"] for row in replay(companion_log, tmp_path / "all").nav if row["would_send"]]
    distinct = sorted(set(ages))
    assert len(distinct) > 1, "the flight's fixes came at one age only"
    halfway = [(a + b) / 2.0 for a, b in itertools.pairwise(distinct)]
    limit = min(halfway, key=lambda cut: abs(sum(age <= cut for age in ages) - len(ages) / 2.0))
    summary = replay(companion_log, tmp_path / "limited", max_reckoning_s=limit).summary
    assert 0 < summary["vs_sent"]["would_send"] < summary["vs_sent"]["states"]


def test_a_truncated_last_line_and_bad_messages_are_skipped_and_named(
    companion_log: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    lines = companion_log.read_text().splitlines()
    bad_type = json.dumps(
        {"kind": "recv", "time_s": json.loads(lines[3])["time_s"], "msg": {"mavpackettype": "NOPE"}}
    )
    broken = json.loads(next(line for line in lines if '"GLOBAL_POSITION_INT"' in line))
    del broken["msg"]["lat"]
    edited = [*lines[:3], bad_type, json.dumps(broken), *lines[3:-1], lines[-1][: len(lines[-1]) // 2]]
    path = tmp_path / "crashed.jsonl"
    path.write_text("\n".join(edited))  # no newline at the end: the companion stopped mid-write
    with caplog.at_level(logging.WARNING):
        summary = replay(path, tmp_path / "out").summary
    assert summary["skipped_lines"] == {
        "unknown message type": 1,
        "malformed GLOBAL_POSITION_INT message": 1,
        "truncated last line (the companion stopped mid-write)": 1,
    }
    assert "line 4: unknown message type (NOPE)" in caplog.text and "line 5: malformed" in caplog.text
    assert f"line {len(edited)}: truncated" in caplog.text
    assert summary["vs_sent"]["position_offset_m"]["max"] < 0.05  # one lost sample changes nothing


def test_a_log_without_fixes_is_dead_reckoning_only(companion_log: Path, tmp_path: Path) -> None:
    path = tmp_path / "nofix.jsonl"
    path.write_text(
        "".join(line + "\n" for line in companion_log.read_text().splitlines() if '"kind": "fix"' not in line)
    )
    summary = replay(path, tmp_path / "out").summary
    assert summary["fixes"]["frames"] == 0 and summary["time_s"]["fixed"] == 0.0
    assert summary["time_s"]["dead reckoning"] > RUN_S / 2
    assert (tmp_path / "out" / "replay.png").exists()


def test_files_that_are_not_companion_logs_get_clear_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty.jsonl"
    empty.write_text("\n\n")
    with pytest.raises(OrthonavError, match=r"empty\.jsonl: empty"):
        read_companion_log(empty)
    fixes = tmp_path / "fixes.jsonl"
    fixes.write_text(json.dumps(Fix(False, reason="no match").to_dict()) + "\n")
    with pytest.raises(OrthonavError, match="line 1: not a companion log"):
        read_companion_log(fixes)
    binary = tmp_path / "flight.jsonl"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(OrthonavError, match="not a companion log"):
        read_companion_log(binary)
    no_start = tmp_path / "nostart.jsonl"
    no_start.write_text(json.dumps({"kind": "recv", "time_s": 1.0, "msg": {}}) + "\n")
    with pytest.raises(OrthonavError, match="open with a 'start' record"):
        read_companion_log(no_start)
    silent = tmp_path / "silent.jsonl"
    silent.write_text(json.dumps({"kind": "start", "time_s": 1.0, "config": {}}) + "\n")
    with pytest.raises(OrthonavError, match="received no telemetry"):
        read_companion_log(silent)
    with pytest.raises(OrthonavError, match=r"--run 2: .* holds 1 run"):
        read_companion_log(silent, run=2)
    result = CliRunner().invoke(app, ["replay", str(tmp_path / "missing.jsonl")])
    expect_error(result, "missing.jsonl: no such file")


def test_fix_round_trips_through_its_dict() -> None:
    pose = Pose(47.01, -99.12, 1000.0, 91.5, 1.25, -0.5, 47.0101, -99.1199)
    accepted = Fix(
        True,
        "",
        pose,
        np.array([[16.25, 1.5], [1.5, 9.0]]),
        {"inliers": 42.0, "rmse_px": 1.25},
        {"total_ms": 80.5},
        "orb",
    )
    again = Fix.from_dict(json.loads(json.dumps(accepted.to_dict())))
    assert again.pose == pose and np.array_equal(again.covariance_enu_m2, accepted.covariance_enu_m2)
    assert (again.quality, again.timings_ms, again.method) == (accepted.quality, accepted.timings_ms, "orb")
    assert again.to_dict() == accepted.to_dict()
    rejected = Fix(False, "only 8 inliers", pose, None, {"inliers": 8.0})
    back = Fix.from_dict(rejected.to_dict())
    assert not back.accepted and back.pose == pose and back.reason == "only 8 inliers"
    assert back.to_dict() == rejected.to_dict()
    assert Fix.from_dict(Fix(False, "dark").to_dict()).pose is None
    with pytest.raises(OrthonavError, match=r"fix record: expected the fields of Fix\.to_dict"):
        Fix.from_dict({**accepted.to_dict(), "lat": None})
    with pytest.raises(OrthonavError, match="fix record"):
        Fix.from_dict({"reason": "no accepted"})
