"""``orthonav simulate`` and ``orthonav demo``: the navigation mission over a map."""

from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import typer

from orthonav.cli.inputs import FIX_SOURCE_HELP, fix_source_option, parse_latlon
from orthonav.cli.output import console, print_dict, say, say_fix_source


def simulate(
    map_dir: Annotated[Path, typer.Argument(help="Map package directory.")],
    start: Annotated[str, typer.Option(help="Start zone centre LAT,LON.")],
    target: Annotated[str, typer.Option(help="Target LAT,LON.")],
    frames_from: Annotated[
        Path | None, typer.Option(help="Render frames from this GeoTIFF (e.g. another year).")
    ] = None,
    out: Annotated[Path, typer.Option(help="Run directory.")] = Path("runs/mission"),
    speed: Annotated[float, typer.Option(help="Ground speed (m/s).")] = 20.0,
    step: Annotated[float, typer.Option(help="Time between frames (s).")] = 5.0,
    max_time: Annotated[float, typer.Option(help="Flight time limit (s).")] = 1200.0,
    arrival_radius: Annotated[
        float, typer.Option(help="Arrived when the estimate is this close (m).")
    ] = 60.0,
    altitude: Annotated[
        float | None, typer.Option(help="Altitude AGL (m); default: the map's nominal.")
    ] = None,
    start_zone: Annotated[float, typer.Option(help="Radius of the start zone (m).")] = 100.0,
    photometric: Annotated[float, typer.Option(help="Photometric change strength 0..1.5.")] = 0.6,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    save_frames: Annotated[bool, typer.Option(help="Save every frame as JPEG.")] = False,
    imu: Annotated[str, typer.Option(help="IMU error model: perfect, tactical, consumer.")] = "consumer",
    gnss_loss: Annotated[
        float, typer.Option(help="GNSS is lost this many seconds after the start (0: from the start).")
    ] = 0.0,
    fix_latency: Annotated[float, typer.Option(help="Frame capture to fix delivery (s).")] = 0.5,
    fix_source: Annotated[str | None, typer.Option(help=FIX_SOURCE_HELP)] = None,
) -> None:
    """Fly the mission loop (INS + visual fixes + filter) over a map; write logs, plot and summary."""
    from orthonav.geo import GeoRaster
    from orthonav.localize import open_fix_sources, warm_up_maps
    from orthonav.mapdb import MapPackage
    from orthonav.sim import SIMULATED_WORLD, MissionConfig, run_mission

    package = MapPackage(map_dir)
    source = frames_from or package.source_path
    config = MissionConfig(
        *parse_latlon(start, "--start"),
        *parse_latlon(target, "--target"),
        speed_mps=speed,
        step_s=step,
        max_time_s=max_time,
        arrival_radius_m=arrival_radius,
        alt_agl_m=altitude,
        start_zone_m=start_zone,
        photometric_strength=photometric,
        seed=seed,
        save_frames=save_frames,
        imu=imu,
        gnss_loss_s=gnss_loss,
        fix_latency_s=fix_latency,
    )
    with ExitStack() as stack:
        frames = stack.enter_context(GeoRaster(source))
        # Frames rendered from an orthophoto see flat ground (SIMULATED_WORLD), as run_mission's own.
        name = fix_source_option(fix_source)
        opened = open_fix_sources(stack, package, package.camera, name, localizer=SIMULATED_WORLD)
        say_fix_source(opened)
        say(warm_up_maps(opened, package.camera))
        result = run_mission(package, frames, package.camera, config, out, fix_source=opened.source)
    print_dict("mission", result.summary())


def demo(
    out: Annotated[Path, typer.Option(help="Output directory.")] = Path("orthonav-demo"),
    map_tif: Annotated[Path | None, typer.Option("--map", help="Fly over this GeoTIFF instead.")] = None,
    frames_from: Annotated[Path | None, typer.Option(help="Render frames from this GeoTIFF.")] = None,
    altitude: Annotated[float | None, typer.Option(help="Altitude AGL (m).")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
) -> None:
    """Build a map of built-in synthetic terrain (or --map) and fly a mission over it."""
    from orthonav.sim import run_demo

    result = run_demo(out, map_tif, frames_from, altitude, seed)
    print_dict("demo mission", result.summary())
    console.print(
        f"outputs: {out / 'run'} (trajectory.png, steps.jsonl, summary.json); map: {out / 'map'}",
        soft_wrap=True,
    )
