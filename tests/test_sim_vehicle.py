"""The simulated MAVLink vehicle over the real NAIP orthophoto: telemetry, frames, grading, drift."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

pytest.importorskip("pymavlink")

from conftest import CAMERA, NAIP_ALT_M, naip_path
from typer import Typer
from typer.testing import CliRunner

from orthonav.cli.vehicle import sim_vehicle
from orthonav.errors import OrthonavError
from orthonav.frames import capture_time_from_name
from orthonav.fusion import NavState
from orthonav.geo import GeoRaster, LocalFrame, destination, distance_m
from orthonav.mavlink import messages
from orthonav.mavlink.link import MavLink, dialect
from orthonav.mavlink.telemetry import Telemetry
from orthonav.vehicle.simulated import SimVehicle, SimVehicleConfig

FRAMES_YEAR = "20180716"  # another year than the 2020 map
OFFSET_M = 30.0


@pytest.fixture(scope="module")
def frames_raster() -> Iterator[GeoRaster]:
    with GeoRaster(naip_path(FRAMES_YEAR)) as raster:
        yield raster


def config_over(raster: GeoRaster, **changes: Any) -> SimVehicleConfig:
    """East from the raster's centre to a target 1.5 km away."""
    lat, lon = raster.center_latlon
    target = destination(lat, lon, 90.0, 1500.0)
    return SimVehicleConfig(lat, lon, *target, **{"alt_agl_m": NAIP_ALT_M, **changes})


def state_at(lat: float, lon: float, time_s: float) -> NavState:
    return NavState(
        time_s, lat, lon, 90.0, 15.0, 0.0, np.diag([16.0, 16.0]), 2.0, "fixed", 0.0, float(NAIP_ALT_M)
    )


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


class Companion:
    """The test's side of the link: collects telemetry and keeps the messages by type."""

    def __init__(self) -> None:
        self.link = MavLink("udpin:127.0.0.1:0").open()
        self.telemetry = Telemetry(max_age_s=2.0)
        self.seen: dict[str, list[Any]] = {}

    def poll_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            for msg in self.link.poll():
                self.telemetry.ingest(msg, time.time())
                self.seen.setdefault(msg.get_type(), []).append(msg)
            time.sleep(0.01)

    def poll_until(self, ready: Callable[[], bool], timeout_s: float) -> None:
        """Poll until ``ready()`` or ``timeout_s``: on a busy machine the vehicle's first messages
        (its origin among them) may come later than on an idle one."""
        deadline = time.monotonic() + timeout_s
        while not ready() and time.monotonic() < deadline:
            self.poll_for(0.1)

    def count(self, kind: str) -> int:
        return len(self.seen.get(kind, []))


def test_vehicle_streams_telemetry_renders_frames_and_grades_what_it_is_sent(
    frames_raster: GeoRaster, tmp_path: Path
) -> None:
    config = config_over(frames_raster, gnss_loss_s=60.0, frame_rate_hz=4.0)  # GNSS all along
    companion = Companion()
    vehicle_link = MavLink(f"udpout:127.0.0.1:{companion.link.local_port}", role="vehicle")
    vehicle = SimVehicle(config, vehicle_link, frames_raster, CAMERA, tmp_path / "frames", tmp_path / "out")
    thread = threading.Thread(target=vehicle.run, args=(6.0,))
    started = time.time()
    thread.start()
    try:
        companion.poll_for(1.2)
        tel = companion.telemetry
        companion.poll_until(lambda: tel.origin() is not None and tel.latest("GLOBAL_POSITION_INT"), 5.0)
        send_graded_messages(companion)
        companion.poll_for(1.5)
    finally:
        vehicle.stop()
        thread.join(timeout=10.0)
        companion.link.close()
        vehicle_link.close()
    assert not thread.is_alive()
    ended = time.time()
    check_telemetry(companion, config, ended - started)
    check_frames(tmp_path / "frames", started, ended)
    check_grading(tmp_path / "out")


def send_graded_messages(companion: Companion) -> None:
    """GPS_INPUT 30 m east of the reported (= true, GNSS works) position at its time, a vision
    estimate 30 m north, odometry on it, a GPS_INPUT without a fix, a status text and a heartbeat."""
    tel, link = companion.telemetry, companion.link
    # On either clock: on a busy machine SYSTEM_TIME can disagree with ours by more than
    # telemetry's UNIX_MATCH_S, and arrival times are then used (both map boot time to ours).
    position = tel.latest("GLOBAL_POSITION_INT")
    assert position is not None
    capture_s = tel.boot_to_unix(position.time_boot_ms)
    lat, lon = position.lat * 1e-7, position.lon * 1e-7
    origin = tel.origin()
    assert origin is not None
    link.send(
        messages.gps_input(state_at(*destination(lat, lon, 90.0, OFFSET_M), capture_s), capture_s, 700.0)
    )
    link.send(
        messages.vision_position_estimate(
            state_at(*destination(lat, lon, 0.0, OFFSET_M), capture_s), origin, capture_s
        )
    )
    link.send(messages.odometry(state_at(lat, lon, capture_s), origin, capture_s))
    no_fix = messages.gps_input(state_at(lat, lon, capture_s), capture_s, 700.0)
    no_fix.fix_type = 0
    link.send(no_fix)
    link.statustext(4, "orthonav: hello vehicle")
    link.heartbeat()


def check_telemetry(companion: Companion, config: SimVehicleConfig, run_s: float) -> None:
    for kind in ("ATTITUDE", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "VFR_HUD"):
        assert companion.count(kind) >= 0.5 * config.telemetry_rate_hz * run_s, kind
    assert companion.count("HEARTBEAT") >= 2 and companion.count("SYSTEM_TIME") >= 2
    beat = companion.seen["HEARTBEAT"][0]
    assert beat.autopilot == dialect().MAV_AUTOPILOT_ARDUPILOTMEGA
    assert companion.telemetry.origin() == pytest.approx((config.start_lat, config.start_lon), abs=1e-7)
    # Flying east at the configured speed, on the unix clock of its time stamps.
    first, last = companion.seen["GLOBAL_POSITION_INT"][0], companion.seen["GLOBAL_POSITION_INT"][-1]
    flown_m = distance_m(first.lat * 1e-7, first.lon * 1e-7, last.lat * 1e-7, last.lon * 1e-7)
    elapsed_s = (last.time_boot_ms - first.time_boot_ms) / 1000.0
    assert flown_m == pytest.approx(config.speed_mps * elapsed_s, rel=0.05)
    assert last.hdg == pytest.approx(9000, abs=100) and last.relative_alt == NAIP_ALT_M * 1000


def check_frames(frames_dir: Path, started: float, ended: float) -> None:
    names = sorted(p.name for p in frames_dir.iterdir())
    assert not [n for n in names if n.startswith(".")]  # no temporary files left behind
    assert len(names) >= 6  # 4 Hz for ~2.7 s
    for name in names:
        capture_s = capture_time_from_name(Path(name))
        assert capture_s is not None and started <= capture_s <= ended
    image = cv2.imread(str(frames_dir / names[-1]))
    assert image.shape == (CAMERA.height, CAMERA.width, 3)
    assert float(image.std()) > 5.0  # real imagery, not an empty frame


def check_grading(out: Path) -> None:
    records = read_jsonl(out / "received.jsonl")
    by_type: dict[str, list[dict]] = {}
    for record in records:
        by_type.setdefault(record["type"], []).append(record)
    fixed, unfixed = by_type["GPS_INPUT"]
    assert fixed["error_m"] == pytest.approx(OFFSET_M, abs=0.5)
    assert (fixed["error_east_m"], fixed["error_north_m"]) == (
        pytest.approx(OFFSET_M, abs=0.5),
        pytest.approx(0.0, abs=0.5),
    )
    assert fixed["fix_type"] == 3 and fixed["horiz_accuracy_m"] == pytest.approx(4.0)
    assert 0.0 < fixed["age_s"] < 2.0
    assert unfixed["fix_type"] == 0 and "error_m" not in unfixed
    (vision,) = by_type["VISION_POSITION_ESTIMATE"]
    assert vision["error_north_m"] == pytest.approx(OFFSET_M, abs=0.5) and vision["sigma_north_m"] == 4.0
    (odometry,) = by_type["ODOMETRY"]
    assert odometry["error_m"] < 0.5
    (text,) = by_type["STATUSTEXT"]
    assert (text["text"], text["severity"]) == ("orthonav: hello vehicle", 4)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["received"]["GPS_INPUT"] == 2 and summary["received"]["HEARTBEAT"] == 1
    assert summary["gps_input_fix_types"] == {"0": 1, "3": 1} and summary["positions_with_3d_fix"] == 1
    assert summary["errors"]["GPS_INPUT"]["median_m"] == pytest.approx(OFFSET_M, abs=0.5)
    assert summary["frames"] == len(list((out.parent / "frames").iterdir()))
    assert summary["link"]["sent"] > 0 and summary["ins_error_m"] == 0.0
    assert json.loads((out / "config.json").read_text())["vehicle"]["gnss_loss_s"] == 60.0


def fly(vehicle: SimVehicle, until_s: float, step_s: float = 0.05) -> list[float]:
    """Drive the flight on a simulated clock; the distance autopilot belief -> truth per step."""
    vehicle.begin(0.0)
    gaps = []
    for now in np.arange(step_s, until_s + step_s / 2, step_s):
        vehicle.advance(float(now))
        gaps.append(float(distance_m(vehicle.nav.lat, vehicle.nav.lon, vehicle.kin.lat, vehicle.kin.lon)))
    return gaps


def test_ins_drifts_after_gnss_loss_and_the_vehicle_steers_on_its_belief(
    frames_raster: GeoRaster, tmp_path: Path
) -> None:
    def vehicle(imu: str) -> SimVehicle:
        config = config_over(frames_raster, gnss_loss_s=10.0, imu=imu, seed=3)
        return SimVehicle(config, MavLink("udpin:127.0.0.1:0"), frames_raster, CAMERA, tmp_path, tmp_path)

    consumer = fly(vehicle("consumer"), 120.0)
    assert max(consumer[:199]) == 0.0  # the first 10 s: GNSS, the belief is the truth
    assert consumer[-1] > 10.0  # then a consumer IMU drifts
    perfect = vehicle("perfect")
    assert max(fly(perfect, 120.0)) < 0.5
    # It flew to the target and stays around it (turning back over it).
    config = perfect.config
    assert distance_m(perfect.kin.lat, perfect.kin.lon, config.target_lat, config.target_lon) < 400.0
    frame = LocalFrame(config.start_lat, config.start_lon)
    east, north = frame.to_enu(perfect.kin.lat, perfect.kin.lon)
    assert float(east) > 1000.0 and abs(float(north)) < 400.0


def test_start_or_target_off_the_imagery_and_bad_settings_are_rejected(frames_raster: GeoRaster) -> None:
    lat, lon = frames_raster.center_latlon
    far = SimVehicleConfig(lat, lon, *destination(lat, lon, 0.0, 20_000.0))
    with pytest.raises(OrthonavError, match=r"target .* is outside"):
        SimVehicle(far, MavLink("udpin:127.0.0.1:0"), frames_raster, CAMERA, Path("f"), Path("o"))
    with pytest.raises(OrthonavError, match="IMU preset 'mems'"):
        config_over(frames_raster, imu="mems")
    with pytest.raises(OrthonavError, match="speed_mps"):
        config_over(frames_raster, speed_mps=-1.0)
    with pytest.raises(OrthonavError, match="gnss_loss_s"):
        config_over(frames_raster, gnss_loss_s=float("nan"))


def test_cli_command_flies_and_writes_its_results(frames_raster: GeoRaster, tmp_path: Path) -> None:
    app = Typer()
    app.command()(sim_vehicle)
    lat, lon = frames_raster.center_latlon
    target = destination(lat, lon, 45.0, 1000.0)
    # A listener that answers whoever sends (whom a companion believes is tested with the link).
    with MavLink("udpin:127.0.0.1:0", role="vehicle") as listener:
        args = [
            "--frames-from",
            str(naip_path(FRAMES_YEAR)),
            "--frames-dir",
            str(tmp_path / "frames"),
            "--start",
            f"{lat},{lon}",
            "--target",
            f"{target[0]},{target[1]}",
            "--connect",
            f"udpout:127.0.0.1:{listener.local_port}",
            "--duration",
            "1.2",
            "--imu",
            "tactical",
            "--altitude",
            "800",
            "--out",
            str(tmp_path / "out"),
        ]
        result = CliRunner().invoke(app, args)
        assert result.exit_code == 0, result.output
        assert "HEARTBEAT" in [m.get_type() for m in listener.poll(500)]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["frames"] >= 2 and summary["link"]["sent"] > 10
    assert "{'" not in result.output and "link sent" in result.output, result.output  # a table
    assert len(list((tmp_path / "frames").iterdir())) == summary["frames"]
    bad = CliRunner().invoke(app, [*args[:4], "--start", "91,0", *args[6:]])
    assert bad.exit_code != 0 and "--start" in str(bad.exception)
