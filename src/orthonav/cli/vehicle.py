"""``orthonav sim-vehicle``: a simulated autopilot to run ``orthonav fly`` against on one machine."""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Annotated

import typer

from orthonav.cli.inputs import camera_from_options, parse_latlon
from orthonav.cli.output import print_dict


def sim_vehicle(
    frames_from: Annotated[
        Path,
        typer.Option(help="GeoTIFF the camera frames are rendered from (e.g. another year than the map)."),
    ],
    start: Annotated[str, typer.Option(help="Start (and EKF origin) as LAT,LON.")],
    target: Annotated[str, typer.Option(help="Target as LAT,LON.")],
    frames_dir: Annotated[
        Path | None, typer.Option(help="Folder the frames are written to (fly --frames DIR).")
    ] = None,
    stream_port: Annotated[
        int | None,
        typer.Option(
            help="Also (or instead) serve the camera as MJPEG over HTTP on this port: "
            "fly --frames http://127.0.0.1:PORT/camera.mjpg."
        ),
    ] = None,
    stream_host: Annotated[
        str, typer.Option(help="Address the camera stream listens on (0.0.0.0: every interface).")
    ] = "127.0.0.1",
    connect: Annotated[
        str,
        typer.Option(
            help="MAVLink URL: udpout:127.0.0.1:14550 pairs with fly --connect udpin:0.0.0.0:14550."
        ),
    ] = "udpout:127.0.0.1:14550",
    speed: Annotated[float, typer.Option(help="Ground speed (m/s).")] = 15.0,
    altitude: Annotated[float, typer.Option(help="Altitude above ground (m).")] = 300.0,
    ground_alt: Annotated[float, typer.Option(help="Ground altitude above mean sea level (m).")] = 100.0,
    gnss_loss: Annotated[
        float, typer.Option(help="Seconds after start when GNSS is lost (0: from the start).")
    ] = 0.0,
    imu: Annotated[
        str, typer.Option(help="IMU grade of the drifting INS: consumer, tactical, perfect.")
    ] = "consumer",
    duration: Annotated[
        float | None, typer.Option(help="Stop after this many seconds (default: Ctrl-C).")
    ] = None,
    frame_rate: Annotated[float, typer.Option(help="Camera frames per second.")] = 2.0,
    telemetry_rate: Annotated[float, typer.Option(help="Telemetry messages per second (each type).")] = 10.0,
    camera_json: Annotated[Path | None, typer.Option("--camera", help="Camera JSON.")] = None,
    width: Annotated[int, typer.Option(help="Frame width (px) without --camera.")] = 640,
    height: Annotated[int, typer.Option(help="Frame height (px) without --camera.")] = 480,
    hfov: Annotated[float, typer.Option(help="Horizontal field of view (deg) without --camera.")] = 60.0,
    seed: Annotated[int, typer.Option(help="Random seed (IMU errors, photometric changes).")] = 0,
    system: Annotated[int, typer.Option(help="The vehicle's MAVLink system id.")] = 1,
    out: Annotated[Path, typer.Option(help="Where received.jsonl and summary.json go.")] = Path(
        "runs/sim-vehicle"
    ),
) -> None:
    """Fly start -> target in real time, stream telemetry, render frames, grade the positions sent back."""
    from orthonav.errors import OrthonavError
    from orthonav.frames import MjpegServer
    from orthonav.geo import GeoRaster
    from orthonav.mavlink.link import MavLink
    from orthonav.vehicle.simulated import SimVehicle, SimVehicleConfig

    logging.getLogger("orthonav").setLevel(logging.INFO)
    start_lat, start_lon = parse_latlon(start, "--start")
    target_lat, target_lon = parse_latlon(target, "--target")
    config = SimVehicleConfig(
        start_lat,
        start_lon,
        target_lat,
        target_lon,
        speed_mps=speed,
        alt_agl_m=altitude,
        ground_alt_msl_m=ground_alt,
        gnss_loss_s=gnss_loss,
        imu=imu,
        frame_rate_hz=frame_rate,
        telemetry_rate_hz=telemetry_rate,
        seed=seed,
    )
    if frames_dir is None and stream_port is None:
        raise OrthonavError("sim-vehicle: give --frames-dir DIR, --stream-port PORT, or both")
    camera = camera_from_options(camera_json, width, height, hfov)
    stream = MjpegServer(stream_port, stream_host) if stream_port is not None else None
    with (
        GeoRaster(frames_from) as raster,
        MavLink(connect, source_system=system, role="vehicle") as link,
        stream or contextlib.nullcontext(),  # a port in use fails here, before the flight
    ):
        vehicle = SimVehicle(config, link, raster, camera, frames_dir, out, stream)
        outputs = [str(frames_dir)] if frames_dir is not None else []
        outputs += [stream.url] if stream is not None else []
        typer.echo(f"sim-vehicle: {connect}, frames -> {' and '.join(outputs)}, log -> {out}; Ctrl-C stops")
        summary = vehicle.run(duration)
    print_dict(f"sim-vehicle: {out / 'summary.json'}", summary)
