"""The sim vehicle's camera as a live MJPEG-over-HTTP stream, read by the companion like an IP camera.

Over the real NAIP 2020 orthophoto: the companion reads ``http://127.0.0.1:PORT/camera.mjpg``
through OpenCV's FFmpeg backend (``open_live_source``), stamps each frame with its receive time,
localizes, fuses and sends GPS_INPUT back; the vehicle grades it. The same flight through the
watched folder is the reference. Also: clients that go away mid-stream, a clean shutdown, a port
in use, and the ``sim-vehicle --stream-port`` command as its own process.
"""

from __future__ import annotations

import dataclasses
import json
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pymavlink")

from conftest import CAMERA, NAIP_ALT_M, naip_path
from typer import Typer
from typer.testing import CliRunner

from orthonav.cli.vehicle import sim_vehicle
from orthonav.errors import OrthonavError
from orthonav.frames import capture_time_from_name, open_live_source
from orthonav.frames.mjpeg import BOUNDARY, MjpegServer
from orthonav.geo import GeoRaster, destination
from orthonav.localize import Localizer
from orthonav.mapdb import MapPackage
from orthonav.mavlink.companion import Companion, CompanionConfig
from orthonav.mavlink.link import MavLink
from orthonav.vehicle.loopback import VEHICLE_EXTRA_S, fly_loopback
from orthonav.vehicle.simulated import SimVehicle, SimVehicleConfig

COMPANION_S = 8.0


def vehicle_config(raster: GeoRaster) -> SimVehicleConfig:
    """GNSS lost from the start, 20 m/s east across the NAIP quarter-quad, frames at 2 Hz."""
    lat, lon = raster.center_latlon
    start, target = destination(lat, lon, 270.0, 700.0), destination(lat, lon, 90.0, 1000.0)
    return SimVehicleConfig(*start, *target, speed_mps=20.0, alt_agl_m=NAIP_ALT_M, frame_rate_hz=2.0)


def free_tcp_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def read_jsonl(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def fly_over_stream(naip_map: MapPackage, raster: GeoRaster, root: Path) -> tuple[dict, dict]:
    """``fly_loopback`` with the camera as a stream; frames also go to a folder, whose names carry
    the true capture times to compare the stream's receive stamps with."""
    companion_link = MavLink("udpin:127.0.0.1:0", role="companion").open()
    vehicle_link = MavLink(f"udpout:127.0.0.1:{companion_link.local_port}", role="vehicle")
    stream = MjpegServer(0).open()
    vehicle = SimVehicle(
        vehicle_config(raster), vehicle_link, raster, CAMERA, root / "frames", root / "vehicle", stream
    )
    result: dict = {}
    thread = threading.Thread(
        target=lambda: result.update(vehicle.run(COMPANION_S + VEHICLE_EXTRA_S)), daemon=True
    )
    thread.start()
    try:
        source = open_live_source(stream.url)
        config = CompanionConfig(duration_s=COMPANION_S)
        log_path = root / "companion" / "companion.jsonl"
        companion = Companion(config, companion_link, source, Localizer(naip_map, CAMERA), log_path).run()
    except BaseException:
        vehicle.stop()
        raise
    finally:
        thread.join(timeout=COMPANION_S + 30.0)
        vehicle_link.close()
    assert not thread.is_alive()
    return result, companion


@pytest.fixture(scope="module")
def runs(naip_map: MapPackage, naip_raster: GeoRaster, tmp_path_factory) -> dict:
    """The same flight with the camera as a stream and as a watched folder."""
    stream_root = tmp_path_factory.mktemp("over_stream")
    folder_root = tmp_path_factory.mktemp("over_folder")
    stream_vehicle, stream_companion = fly_over_stream(naip_map, naip_raster, stream_root)
    folder_vehicle, folder_companion = fly_loopback(
        Localizer(naip_map, CAMERA),
        naip_raster,
        CAMERA,
        vehicle_config(naip_raster),
        CompanionConfig(duration_s=COMPANION_S),
        folder_root,
    )
    return {
        "stream": (stream_vehicle, stream_companion, stream_root),
        "folder": (folder_vehicle, folder_companion, folder_root),
    }


def test_companion_reading_the_stream_fixes_as_well_as_from_the_folder(runs: dict) -> None:
    stream_vehicle, stream_companion, _ = runs["stream"]
    folder_vehicle, folder_companion, _ = runs["folder"]
    print(f"\nstream: vehicle {stream_vehicle}\ncompanion {stream_companion}")
    print(f"folder: vehicle {folder_vehicle['errors']}\ncompanion {folder_companion}")
    assert stream_companion["fused"] >= 5 and stream_companion["sent"] >= 20
    assert stream_vehicle["received"]["GPS_INPUT"] == stream_companion["sent"]
    assert stream_vehicle["positions_with_3d_fix"] == stream_companion["sent"]
    stream_errors = stream_vehicle["errors"]["GPS_INPUT"]
    folder_errors = folder_vehicle["errors"]["GPS_INPUT"]
    assert stream_errors["median_m"] < 15.0 and stream_errors["max_m"] < 60.0
    assert stream_errors["median_m"] <= 1.5 * folder_errors["median_m"] + 2.0
    assert stream_companion["fused"] >= 0.7 * folder_companion["fused"]
    # One client (the companion) the whole flight, every frame published; closed at the end.
    assert stream_vehicle["stream"]["clients"] == 1
    assert stream_vehicle["stream"]["frames"] == stream_vehicle["frames"] >= 2.0 * COMPANION_S


def test_stream_frames_are_stamped_on_receipt_shortly_after_capture(runs: dict) -> None:
    """The filter fuses each fix at the frame's receive time: later than the true capture by the
    render, JPEG and loopback time only (Content-Length parts: not one frame period later)."""
    _, _, root = runs["stream"]
    captured = np.sort([capture_time_from_name(p) for p in (root / "frames").iterdir()])
    fixes = [r for r in read_jsonl(root / "companion" / "companion.jsonl") if r["kind"] == "fix"]
    assert len(fixes) >= 5
    stamps = np.array([r["capture_time_s"] for r in fixes])
    true_capture = captured[np.searchsorted(captured, stamps, side="right") - 1]
    late_s = stamps - true_capture
    median_ms, max_ms = 1000 * float(np.median(late_s)), 1000 * float(late_s.max())
    print(f"\nreceive stamp - true capture: median {median_ms:.0f} ms, max {max_ms:.0f} ms")
    assert np.all(late_s > 0.0) and float(np.median(late_s)) < 0.15 and float(late_s.max()) < 0.4


@pytest.fixture
def streaming_vehicle(naip_raster: GeoRaster, tmp_path: Path):
    """A vehicle serving its camera on a free port for 4 s (its MAVLink goes to a silent port)."""
    stream = MjpegServer(0).open()
    config = dataclasses.replace(vehicle_config(naip_raster), frame_rate_hz=5.0)
    link = MavLink(f"udpout:127.0.0.1:{free_tcp_port()}", role="vehicle")
    vehicle = SimVehicle(config, link, naip_raster, CAMERA, None, tmp_path / "vehicle", stream)
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(vehicle.run(4.0)), daemon=True)
    thread.start()
    yield stream, thread, result
    vehicle.stop()
    thread.join(timeout=15.0)
    link.close()


def read_first_part(sock: socket.socket) -> bytes:
    """The first multipart part's JPEG bytes (after the HTTP head), read by its Content-Length."""
    buffer = b""
    while b"\r\n\r\n" not in buffer.partition(b"Content-Length")[2]:
        buffer += sock.recv(4096)
    head, body = buffer.split(b"\r\n\r\n", 2)[1:]
    length = int(next(line for line in head.split(b"\r\n") if line.startswith(b"Content-Length")).split()[-1])
    while len(body) < length:
        body += sock.recv(65536)
    return body[:length]


def test_clients_going_away_mid_stream_do_not_stop_the_vehicle_and_shutdown_is_clean(
    streaming_vehicle,
) -> None:
    stream, thread, result = streaming_vehicle
    request = f"GET {stream.path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode()
    with socket.create_connection(("127.0.0.1", stream.port), timeout=5.0) as rude:
        rude.sendall(request)
        assert read_first_part(rude)[:2] == b"\xff\xd8"  # a JPEG
        rude.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\x00\x00\x00\x00\x00\x00\x00")
    # closed with a reset, mid-stream; a second one reads half a frame and hangs up
    with socket.create_connection(("127.0.0.1", stream.port), timeout=5.0) as quitter:
        quitter.sendall(request)
        quitter.recv(1000)
    with socket.create_connection(("127.0.0.1", stream.port), timeout=5.0) as wrong:
        wrong.sendall(b"GET /other HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        reply = wrong.recv(4096)
    assert reply.startswith(b"HTTP/1.0 404") and stream.path.encode() in reply
    # A well-behaved client keeps getting frames until the vehicle lands, then a clean end.
    with socket.create_connection(("127.0.0.1", stream.port), timeout=5.0) as client:
        client.sendall(request)
        received = b""
        while chunk := client.recv(65536):
            received += chunk
    frames = received.count(b"Content-Type: image/jpeg")
    assert received.rstrip().endswith(f"--{BOUNDARY}--".encode())
    thread.join(timeout=15.0)
    assert not thread.is_alive() and result, "the vehicle did not finish its flight"
    assert frames >= 5 and result["stream"]["clients"] == 3  # the 404 is no stream client
    assert result["stream"]["disconnects"] >= 2
    assert result["frames"] == result["stream"]["frames"] >= 15  # 5 Hz for 4 s, none missed
    server_threads = [
        t.name for t in threading.enumerate() if "process_request" in t.name or "mjpeg" in t.name
    ]
    assert not server_threads  # the server's and every client's thread ended
    with socket.socket() as again:  # the port is free again
        again.bind(("127.0.0.1", stream.port))


def test_a_port_in_use_or_no_camera_output_is_a_clear_error(naip_raster: GeoRaster, tmp_path: Path) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(OrthonavError, match=rf"127.0.0.1:{port}: the port is already in use"):
            MjpegServer(port).open()
        app = Typer()
        app.command()(sim_vehicle)
        config = vehicle_config(naip_raster)
        args = [
            "--frames-from",
            str(naip_path("20200831")),
            "--start",
            f"{config.start_lat},{config.start_lon}",
            "--target",
            f"{config.target_lat},{config.target_lon}",
            "--connect",
            f"udpout:127.0.0.1:{free_tcp_port()}",
            "--duration",
            "1",
            "--out",
            str(tmp_path / "out"),
        ]
        result = CliRunner().invoke(app, [*args, "--stream-port", str(port)])
    assert isinstance(result.exception, OrthonavError) and "already in use" in str(result.exception)
    assert not (tmp_path / "out").exists()  # failed before flying
    result = CliRunner().invoke(app, args)
    assert isinstance(result.exception, OrthonavError) and "--stream-port" in str(result.exception)
    with pytest.raises(OrthonavError, match=r"port: expected 0\.\.65535"):
        MjpegServer(70000)
    link = MavLink("udpin:127.0.0.1:0")
    with pytest.raises(OrthonavError, match="frames folder, a camera stream"):
        SimVehicle(config, link, naip_raster, CAMERA, None, tmp_path)


def test_sim_vehicle_command_serves_its_camera_to_a_stream_reader(
    naip_raster: GeoRaster, tmp_path: Path
) -> None:
    """``orthonav sim-vehicle --stream-port`` as its own process, read like an IP camera."""
    port = free_tcp_port()
    config = vehicle_config(naip_raster)
    command = [sys.executable, "-m", "orthonav.cli.main", "sim-vehicle"]
    vehicle = subprocess.Popen(
        [
            *command,
            "--frames-from",
            str(naip_path("20200831")),
            "--stream-port",
            str(port),
            "--start",
            f"{config.start_lat},{config.start_lon}",
            "--target",
            f"{config.target_lat},{config.target_lon}",
            "--connect",
            f"udpout:127.0.0.1:{free_tcp_port()}",
            "--frame-rate",
            "4",
            "--duration",
            "5",
            "--out",
            str(tmp_path / "vehicle"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        url = f"http://127.0.0.1:{port}/camera.mjpg"
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline:  # the process imports, then listens
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                break
            except OSError:
                time.sleep(0.2)
        source = open_live_source(url)
        frames = [frame for _ in range(3) if (frame := source.grab(3.0)) is not None]
        source.close()
    finally:
        output, _ = vehicle.communicate(timeout=30)
    assert vehicle.returncode == 0, output[-2000:]
    assert url in output
    assert len(frames) == 3 and frames[-1].image.shape == (CAMERA.height, CAMERA.width, 3)
    assert float(frames[-1].image.std()) > 5.0  # real imagery
    assert frames[0].capture_time_s < frames[1].capture_time_s < frames[2].capture_time_s
    summary = json.loads((tmp_path / "vehicle" / "summary.json").read_text())
    assert summary["stream"]["clients"] >= 1 and summary["stream"]["frames"] == summary["frames"]
    assert json.loads((tmp_path / "vehicle" / "config.json").read_text())["stream"] == url
