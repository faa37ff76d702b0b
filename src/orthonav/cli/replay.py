"""``orthonav replay``: localize a recorded flight against a map and score it against its GNSS."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from orthonav.cli.inputs import DEVICE_HELP, camera_from_options
from orthonav.errors import OrthonavError

if TYPE_CHECKING:
    from orthonav.camera import Camera
    from orthonav.frames import FrameSource
    from orthonav.replay import ReplayResult


def replay(
    flight: Annotated[
        Path,
        typer.Argument(
            help="Flight log (.bin or .tlog), a folder of geotagged (DJI) photos, or a companion log "
            "(fly --log-dir: companion.jsonl) whose navigation filter is re-run."
        ),
    ],
    map_dir: Annotated[
        Path | None, typer.Option("--map", help="Map package directory (logs with frames, photos).")
    ] = None,
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
    features: Annotated[
        str | None, typer.Option(help="Expected feature backend (default: the one that built the map).")
    ] = None,
    device: Annotated[str, typer.Option(help=DEVICE_HELP)] = "cpu",
    imu: Annotated[
        str | None,
        typer.Option(
            help="Companion log: process noise preset consumer|tactical|perfect (default: the log's)."
        ),
    ] = None,
    gate_probability: Annotated[
        float | None, typer.Option(help="Companion log: chi-square gate probability of fixes (0.999).")
    ] = None,
    init_sigma: Annotated[
        float | None, typer.Option(help="Companion log: 1-sigma (m) of the first telemetry position.")
    ] = None,
    gnss_seed: Annotated[
        bool | None,
        typer.Option(
            "--gnss-seed/--no-gnss-seed",
            help="Companion log: before the first visual fix, the autopilot's position while its GNSS "
            "reports a 3-D fix (default: the log's).",
        ),
    ] = None,
    max_sigma: Annotated[
        float | None, typer.Option(help="Companion log: largest 1-sigma (m) a state is sent with.")
    ] = None,
    heading_fix_sigma: Annotated[
        str | None,
        typer.Option(help="Companion log: 1-sigma (deg) of a fix's heading, or 'none' to ignore it."),
    ] = None,
    history: Annotated[
        float | None, typer.Option(help="Companion log: seconds of history, how late a fix may be fused.")
    ] = None,
    run: Annotated[
        int | None,
        typer.Option(help="Companion log: which of its appended runs (1-based; default the last)."),
    ] = None,
    out: Annotated[
        Path,
        typer.Option(
            help="Output folder: replay.jsonl (nav.jsonl for a companion log), summary.json, config.json, "
            "replay.png."
        ),
    ] = (Path("runs/replay")),
) -> None:
    """Replay a flight log with its video/frames (or DJI photos) against a map; error vs the logged GNSS.
    Or re-run the navigation filter of a companion log with other settings."""
    filter_options = {
        "imu": imu,
        "gate_probability": gate_probability,
        "init_sigma_m": init_sigma,
        "gnss_seed": gnss_seed,
        "max_sigma_m": max_sigma,
        "heading_fix_sigma_deg": heading_fix_sigma,
        "history_s": history,
    }
    if flight.suffix.lower() == ".jsonl":
        localizer_options = {
            "--map": map_dir,
            "--frames": frames,
            "--offset": offset,
            "--interval": interval,
            "--camera": camera_json,
            "--hfov": hfov,
            "--features": features,
        }
        _not_for_companion_log(localizer_options)
        _replay_companion_log(flight, filter_options, run, out)
        return
    _only_for_companion_log(filter_options, run)
    if map_dir is None:
        raise OrthonavError(
            f"{flight}: localizing a flight log or photos needs --map (a map package directory)"
        )
    from orthonav.features import Runtime
    from orthonav.flightlog.photos import read_photos
    from orthonav.localize import Localizer, check_backend
    from orthonav.mapdb import MapPackage
    from orthonav.replay import ReplayConfig, camera_for_photos, replay_flight, replay_photos

    package = MapPackage(map_dir)
    if features:
        check_backend(package, features)
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


def _replay_companion_log(path: Path, options: dict, run: int | None, out: Path) -> None:
    from orthonav.replay import read_companion_log, replay_companion_log, settings_from_log

    overrides = {key: value for key, value in options.items() if value is not None}
    if "heading_fix_sigma_deg" in overrides:
        overrides["heading_fix_sigma_deg"] = _degrees_or_none(overrides["heading_fix_sigma_deg"])
    companion_log = read_companion_log(path, run)
    settings = settings_from_log(companion_log.config, overrides)
    result = replay_companion_log(companion_log, settings, out, overrides)
    summary = result.summary
    fixes = summary["fixes"]
    typer.echo(
        f"re-ran {summary['duration_s']:.0f} s: {fixes['fused']} of {fixes['frames']} fixes fused "
        f"(originally {fixes['originally_fused']}, {fixes['verdicts_changed']} verdicts changed)"
    )
    for reason, count in fixes["rejected_reasons"].items():
        typer.echo(f"  rejected {count}: {reason}")
    typer.echo("time: " + ", ".join(f"{key} {value:.0f} s" for key, value in summary["time_s"].items()))
    offset = summary["vs_sent"]["position_offset_m"]
    if offset:
        typer.echo(
            f"re-run vs sent ({offset['count']} states): median {offset['median']:.2f} m, "
            f"max {offset['max']:.2f} m"
        )
    reference = summary["gnss_reference"]
    for key in ("rerun_error_m", "sent_error_m"):
        if reference and reference[key]:
            typer.echo(
                f"{key.removesuffix('_error_m')} error vs GNSS: median {reference[key]['median']:.1f} m"
            )
    skipped = summary["skipped_lines"]
    if skipped:
        typer.echo("skipped lines: " + ", ".join(f"{n} {reason}" for reason, n in skipped.items()))
    typer.echo(f"written: {result.out_dir} (nav.jsonl, summary.json, config.json, replay.png)")


def _degrees_or_none(text: str) -> float | None:
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise OrthonavError(f"--heading-fix-sigma {text!r}: expected degrees > 0 or 'none'") from None


def _not_for_companion_log(options: dict) -> None:
    given = [name for name, value in options.items() if value is not None]
    if given:
        raise OrthonavError(
            f"{', '.join(given)}: a companion log re-runs the navigation filter on its own fixes; "
            "these options localize frames"
        )


def _only_for_companion_log(options: dict, run: int | None) -> None:
    given = [
        f"--{name.removesuffix('_m').removesuffix('_deg').removesuffix('_s').replace('_', '-')}"
        for name, value in options.items()
        if value is not None
    ]
    if run is not None:
        given.append("--run")
    if given:
        raise OrthonavError(f"{', '.join(given)}: filter options apply to a companion log (.jsonl) only")


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
