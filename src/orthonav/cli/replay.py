"""``orthonav replay``: localize a recorded flight against a map and score it against its GNSS."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from orthonav.cli.inputs import camera_from_options
from orthonav.errors import OrthonavError

if TYPE_CHECKING:
    from orthonav.camera import Camera
    from orthonav.frames import FrameSource
    from orthonav.replay import ReplayResult


def replay(
    flight: Annotated[
        Path, typer.Argument(help="Flight log (.bin or .tlog), or a folder of geotagged (DJI) photos.")
    ],
    map_dir: Annotated[Path, typer.Option("--map", help="Map package directory.")],
    frames: Annotated[
        Path | None,
        typer.Option(help="With a log: the flight's video, or its frames' folder (sorted by name)."),
    ] = None,
    offset: Annotated[
        float | None, typer.Option(help="Log time (s, on the log's clock) of the first frame.")
    ] = None,
    interval: Annotated[
        float | None, typer.Option(help="Seconds between the frames of an image folder.")
    ] = None,
    every: Annotated[int, typer.Option(help="Localize every Nth frame or photo.")] = 1,
    camera_json: Annotated[
        Path | None, typer.Option("--camera", help="Camera JSON (default: the photos' EXIF, else the map's).")
    ] = None,
    hfov: Annotated[
        float | None, typer.Option(help="Horizontal field of view (deg) of a --width x --height camera.")
    ] = None,
    width: Annotated[int, typer.Option(help="Frame width (px) with --hfov.")] = 640,
    height: Annotated[int, typer.Option(help="Frame height (px) with --hfov.")] = 480,
    prior_sigma: Annotated[
        str,
        typer.Option(
            help="1-sigma (m) of the position prior at the logged position; 'none' searches every tile."
        ),
    ] = "50",
    nadir_gimbal: Annotated[
        bool, typer.Option(help="The camera hangs in a nadir gimbal: ignore the vehicle's pitch/roll.")
    ] = False,
    backend: Annotated[
        str | None, typer.Option(help="Expected feature backend (default: the one that built the map).")
    ] = None,
    device: Annotated[str, typer.Option(help="Where learned backends run: cpu, cuda or cuda:N.")] = "cpu",
    out: Annotated[
        Path, typer.Option(help="Output folder: replay.jsonl, summary.json, config.json, replay.png.")
    ] = (Path("runs/replay")),
) -> None:
    """Replay a flight log with its video/frames (or DJI photos) against a map; error vs the logged GNSS."""
    from orthonav.features import Runtime
    from orthonav.localize import Localizer, check_backend
    from orthonav.mapdb import MapPackage
    from orthonav.mavlink.photos import read_photos
    from orthonav.replay import ReplayConfig, camera_for_photos, replay_flight, replay_photos

    package = MapPackage(map_dir)
    if backend:
        check_backend(package, backend)
    config = ReplayConfig(every, _sigma(prior_sigma), nadir_gimbal=nadir_gimbal)
    given = camera_from_options(camera_json, width, height, hfov) if camera_json or hfov else None

    def localizer(camera: Camera) -> Localizer:
        return Localizer(package, camera, backend=package.create_backend(Runtime(device)))

    if flight.is_dir():
        _no_frame_options(frames, offset, interval)
        photos = read_photos(flight)
        result = replay_photos(photos, localizer(camera_for_photos(photos, given)), out, config)
    else:
        source = _frame_source(flight, frames, offset, interval)
        result = replay_flight(flight, source, offset, localizer(given or package.camera), out, config)
    _print(result)


def _sigma(text: str) -> float | None:
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        raise OrthonavError(f"--prior-sigma {text!r}: expected metres > 0 or 'none'") from None
    if not (math.isfinite(value) and value > 0):
        raise OrthonavError(f"--prior-sigma {text!r}: expected metres > 0 or 'none'")
    return value


def _no_frame_options(frames: Path | None, offset: float | None, interval: float | None) -> None:
    given = [
        name
        for name, v in (("--frames", frames), ("--offset", offset), ("--interval", interval))
        if v is not None
    ]
    if given:
        raise OrthonavError(
            f"{', '.join(given)}: photos carry their own poses and times; give these with a log"
        )


def _frame_source(
    log_path: Path, frames: Path | None, offset: float | None, interval: float | None
) -> FrameSource:
    from orthonav.frames import open_frames

    if frames is None or offset is None:
        raise OrthonavError(
            f"{log_path}: a flight log needs --frames (video or image folder) and --offset (log time of "
            "the first frame)"
        )
    return open_frames(frames, interval, "--frames", "--interval")


def _print(result: ReplayResult) -> None:
    summary = result.summary
    stats = summary["error_m"]
    typer.echo(
        f"frames localized: {summary['frames']}, fixed: {summary['fixes']} ({summary['fix_rate']:.0%})"
    )
    if stats:
        typer.echo(
            "error vs logged GNSS (m): " + ", ".join(f"{key} {value:.1f}" for key, value in stats.items())
        )
    skipped = {reason: n for reason, n in summary["skipped"].items() if n}
    if skipped:
        typer.echo("skipped: " + ", ".join(f"{n} {reason}" for reason, n in skipped.items()))
    typer.echo(f"written: {result.out_dir} (replay.jsonl, summary.json, config.json, replay.png)")
