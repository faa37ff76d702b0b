"""``orthonav fly``: companion-computer mode against a real or simulated autopilot."""

from __future__ import annotations

import logging
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape

from orthonav.camera import Camera
from orthonav.cli.inputs import (
    FALLBACK_HELP,
    FIX_SOURCE_HELP,
    TRUNK_CHECK_HELP,
    fix_source_option,
    trunk_check_option,
)
from orthonav.cli.output import err_console, print_dict, say, say_fix_source
from orthonav.errors import OrthonavError
from orthonav.frames.live import FolderWatch, LiveSource
from orthonav.localize import CORRELATION, DEFAULT_COARSE_BACKBONE, open_fix_sources, warm_up_maps
from orthonav.mavlink.plausibility import VEHICLE_CLASSES

if TYPE_CHECKING:
    from orthonav.mavlink.companion import CompanionConfig

# A companion's frame interval where no frame rate is given: 2 frames/s.
DEFAULT_FRAME_BUDGET_MS = 500.0

VEHICLE_HELP = ", ".join(
    f"{name} ({limits.max_speed_mps:g} m/s, {limits.max_accel_mps2:g} m/s2)"
    for name, limits in VEHICLE_CLASSES.items()
)


def fly(
    frames: Annotated[
        str,
        typer.Option(
            help="Frames: OpenCV device index (0), video file, stream URL (rtsp://...) or a folder to watch.",
        ),
    ],
    map_dir: Annotated[
        Path | None, typer.Argument(metavar="MAP", help="Map package directory.", show_default=False)
    ] = None,
    connect: Annotated[
        str,
        typer.Option(
            help="MAVLink URL of the autopilot: udpin:0.0.0.0:14550 (pairs with sim-vehicle's default), "
            "tcp:HOST:5760, /dev/ttyACM0..."
        ),
    ] = "udpin:0.0.0.0:14550",
    output: Annotated[
        str,
        typer.Option(
            help="gps_input (ArduPilot GPS1_TYPE=14), vision (VISION_POSITION_ESTIMATE), odometry, or "
            "global_position_sensor (GLOBAL_POSITION_SENSOR: PX4's auxiliary global position, EKF2_AGP*)."
        ),
    ] = "gps_input",
    rate: Annotated[float, typer.Option(help="Navigation messages per second.")] = 5.0,
    max_sigma: Annotated[float, typer.Option(help="Send nothing while the 1-sigma exceeds this (m).")] = 50.0,
    init_sigma: Annotated[
        float, typer.Option(help="Uncertainty of the autopilot's position at start (m).")
    ] = 100.0,
    gnss_seed: Annotated[
        bool,
        typer.Option(
            help="Until the first visual fix, search around the autopilot's position while its GNSS "
            "(GPS_RAW_INT) reports a 3-D fix. Off for a vehicle that may start under GNSS spoofing."
        ),
    ] = True,
    on_spoofing: Annotated[
        str,
        typer.Option(
            help="When the autopilot's position stays far from the visual fixes (a spoofed GNSS): warn "
            "(STATUSTEXT), or switch-gps: also make orthonav's GPS the primary (ArduPilot, --output "
            "gps_input: PARAM_SET GPS_AUTO_SWITCH 0, GPS_PRIMARY), or switch-source: also select EKF3's "
            "ExternalNav source set (ArduPilot, --output vision or odometry: MAV_CMD_SET_EKF_SOURCE_SET "
            "--extnav-source-set, until accepted).",
            metavar="warn|switch-gps|switch-source",
        ),
    ] = "warn",
    extnav_source_set: Annotated[
        int,
        typer.Option(
            help="The EKF3 source set (1-3) whose horizontal position is ExternalNav (EK3_SRCn_POSXY 6), "
            "which --on-spoofing switch-source selects."
        ),
    ] = 2,
    max_reckoning: Annotated[
        float,
        typer.Option(
            help="Send nothing once the last fix's frame is this old (s): the autopilot then dead-reckons "
            "on its own IMU instead of fusing its own velocity handed back."
        ),
    ] = 3.0,
    position_reset_every: Annotated[
        float,
        typer.Option(
            help="The first fix after a span without any also goes out as MAV_CMD_EXTERNAL_POSITION_ESTIMATE "
            "(ArduPilot 4.5+, GPS and ExternalNav outputs), at most once per this many seconds; 0: never."
        ),
    ] = 10.0,
    imu: Annotated[str, typer.Option(help="IMU class for the filter: consumer, tactical.")] = "consumer",
    nadir_gimbal: Annotated[bool, typer.Option(help="The camera stays nadir (ignore roll/pitch).")] = False,
    independent_attitude: Annotated[
        bool,
        typer.Option(
            help="The autopilot's roll and pitch do not follow the positions orthonav sends (a "
            "navigation-grade INS; sim-vehicle's true attitude): a camera fixed to the body has its "
            "correlation fixes used while the autopilot has no GNSS too. Without it they are not."
        ),
    ] = False,
    frame_velocity: Annotated[
        bool | None,
        typer.Option(
            "--frame-velocity/--no-frame-velocity",
            help="Measure the ground velocity between consecutive frames (the image shift of the "
            "level camera, needs --nadir-gimbal), fuse it into the filter, and send GPS_INPUT's speed "
            "accuracy from it; a pair that fits badly or disagrees with the estimate is not fused. "
            "Default: on with --nadir-gimbal.",
        ),
    ] = None,
    vehicle: Annotated[
        str,
        typer.Option(
            help="Vehicle class whose speed and acceleration bound a plausible autopilot velocity: "
            f"{VEHICLE_HELP} or auto (plane for a fixed-wing or VTOL HEARTBEAT)."
        ),
    ] = "auto",
    max_speed: Annotated[
        float | None, typer.Option(help="Fastest plausible ground speed (m/s); default: the vehicle class's.")
    ] = None,
    max_accel: Annotated[
        float | None,
        typer.Option(help="Largest plausible horizontal acceleration (m/s2); default: the vehicle class's."),
    ] = None,
    frame_rate: Annotated[
        float | None, typer.Option(help="Frame rate of a video file played as live (frames/s).")
    ] = None,
    frame_budget_ms: Annotated[
        float | None,
        typer.Option(
            help="Milliseconds the cascade may spend on a frame: once spent, its costly stages "
            "(LightGlue, the second correlation, a lost frame's search) are skipped, and the frame ends "
            "with the pose verified so far or a rejection saying 'deadline'; never an unverified fix. "
            "Default: the frame interval (1000 / --frame-rate), else "
            f"{DEFAULT_FRAME_BUDGET_MS:g} (2 frames/s); 0: unbounded.",
            show_default=False,
        ),
    ] = None,
    camera_json: Annotated[
        Path | None, typer.Option("--camera", help="Camera JSON; default: the map's camera.")
    ] = None,
    fix_source: Annotated[str | None, typer.Option(help=FIX_SOURCE_HELP)] = None,
    fallback: Annotated[list[Path] | None, typer.Option(help=FALLBACK_HELP)] = None,
    coarse_backbone: Annotated[
        str,
        typer.Option(
            help="The cascade's coarse correlations, each asked only where the one before rejects the "
            "frame: gradient (the gradient magnitude), orientation (the gradients' orientation: places "
            "frames of a hazy or reversed-contrast date), trained (the features of "
            "orthonav's trained CNN, a ResNet-18 fitted on aerial photos of several dates: about 100 ms "
            "more a frame on a 2-core CPU), alone or joined by '>'. "
            "The default's second correlation adds fixes across dates; its time is paid only by the "
            "frames the first rejects."
        ),
    ] = DEFAULT_COARSE_BACKBONE,
    trunk_check: Annotated[str, typer.Option(help=TRUNK_CHECK_HELP)] = "auto",
    correlate: Annotated[
        Path | None,
        typer.Option(
            help="--fix-source correlation against this orthophoto instead of the map's own (e.g. "
            "another copy of it); around the filter's estimate, and when lost around the best tiles "
            "of the map's global index (if it has one: orthonav map index --method cnn)."
        ),
    ] = None,
    duration: Annotated[float | None, typer.Option(help="Stop after this many seconds.")] = None,
    out: Annotated[Path, typer.Option(help="Where the JSONL log and summary go.")] = Path("runs/fly"),
    system: Annotated[int, typer.Option(help="Our MAVLink system id (the autopilot's, usually 1).")] = 1,
    component: Annotated[
        int, typer.Option(help="Our MAVLink component id (197 = onboard computer 2).")
    ] = 197,
    target_system: Annotated[
        int | None,
        typer.Option(
            help="The autopilot's MAVLink system id; default: the first that sends an autopilot HEARTBEAT. "
            "Listening (udpin), only it is answered; packets from others are ignored."
        ),
    ] = None,
    target_component: Annotated[
        int | None,
        typer.Option(
            help="The autopilot's MAVLink component id; default: that of the first autopilot HEARTBEAT."
        ),
    ] = None,
    signing_key: Annotated[
        Path | None,
        typer.Option(
            help="MAVLink 2 signing: a file holding the autopilot's 32-byte key as 64 hex digits. "
            "Everything sent is signed; packets unsigned or signed otherwise are refused."
        ),
    ] = None,
    # The names fly had before it took the map and --out as the other commands do; kept working.
    map_option: Annotated[Path | None, typer.Option("--map", hidden=True)] = None,
    log_dir: Annotated[Path | None, typer.Option("--log-dir", hidden=True)] = None,
) -> None:
    """Localize camera frames against the map, fuse them, and feed the autopilot over MAVLink.
    A folder is watched for new frames: the images already in it are passed over as stale."""
    from orthonav.frames import open_live_source
    from orthonav.mapdb import MapPackage
    from orthonav.mavlink.companion import Companion, CompanionConfig
    from orthonav.mavlink.link import MavLink, PeerFilter, dialect, read_signing_key

    dialect()  # without pymavlink, one line naming the extra now, not after the map check and warm-up
    map_dir = _map_given(map_dir, map_option)
    out = log_dir if log_dir is not None else out

    logging.getLogger("orthonav").setLevel(logging.INFO)
    config = CompanionConfig(
        output=output,
        rate_hz=rate,
        max_sigma_m=max_sigma,
        init_sigma_m=init_sigma,
        gnss_seed=gnss_seed,
        on_spoofing=on_spoofing,
        extnav_source_set=extnav_source_set,
        max_reckoning_s=max_reckoning,
        position_reset_interval_s=position_reset_every or None,
        imu=imu,
        nadir_gimbal=nadir_gimbal,
        independent_attitude=independent_attitude,
        frame_velocity=nadir_gimbal if frame_velocity is None else frame_velocity,
        vehicle=vehicle,
        max_speed_mps=max_speed,
        max_accel_mps2=max_accel,
        duration_s=duration,
    )
    _warn_if_body_camera(config)
    peers = PeerFilter(target_system, target_component)
    key = read_signing_key(signing_key) if signing_key is not None else None
    if correlate is not None and fix_source not in (None, CORRELATION):
        raise OrthonavError(
            f"--correlate {correlate} asks for correlation fixes; it cannot go with --fix-source {fix_source}"
        )
    package = MapPackage(map_dir)
    package.require_intact()  # a damaged chunk found in flight would leave the vehicle lost over it
    camera = Camera.from_json(camera_json) if camera_json else package.camera
    with ExitStack() as stack:
        name = CORRELATION if correlate is not None else fix_source_option(fix_source)
        opened = open_fix_sources(
            stack,
            package,
            camera,
            name,
            fallback or [],
            correlate,
            coarse_backbone=coarse_backbone,
            trunk_check=trunk_check_option(trunk_check),
            frame_budget_ms=frame_budget(frame_budget_ms, frame_rate),
        )
        say_fix_source(opened)
        say(warm_up_maps(opened, camera))
        localizer = opened.source
        source = open_live_source(frames, frame_rate)
        link = MavLink(
            connect, source_system=system, source_component=component, peers=peers, signing_key=key
        )
        link.open()
        _say_what_is_awaited(source, connect)
        companion = Companion(config, link, source, localizer, out / "companion.jsonl", camera)
        summary = companion.run()
    print_dict(f"fly: {out / 'summary.json'}", summary)
    if companion.interrupted:
        raise typer.Exit(130)  # Ctrl-C, as every command ends on it


def frame_budget(asked_ms: float | None, frame_rate: float | None) -> float | None:
    """The cascade's frame budget: as asked (0: unbounded), else the frame interval, else
    :data:`DEFAULT_FRAME_BUDGET_MS`: a fix later than the next frame is worth less than that
    frame's."""
    if asked_ms is not None:
        if not asked_ms >= 0.0:
            raise OrthonavError(
                f"--frame-budget-ms: expected milliseconds >= 0 (0: unbounded), got {asked_ms}"
            )
        return asked_ms or None
    if frame_rate is not None and frame_rate > 0:
        return 1000.0 / frame_rate
    return DEFAULT_FRAME_BUDGET_MS


def _map_given(argument: Path | None, option: Path | None) -> Path:
    """The map package, as the argument or as the former --map, not two different ones."""
    if argument is not None and option is not None and argument != option:
        raise OrthonavError(f"fly: the map {argument} and --map {option} name two maps; give one")
    found = argument if argument is not None else option
    if found is None:
        raise OrthonavError("fly: which map? orthonav fly MAP --frames SOURCE")
    return found


def _warn_if_body_camera(config: CompanionConfig) -> None:
    """A camera fixed to the body places its frames by the autopilot's attitude, which without GNSS
    follows orthonav's own positions (``Companion._break_attitude_loop``): most fixes over a
    cross-date map are then refused (docs/benchmarks/sitl.md)."""
    if not (config.nadir_gimbal or config.independent_attitude):
        say(
            [
                "warning: the camera is taken as fixed to the body (no --nadir-gimbal): its correlation "
                "fixes are placed with the autopilot's tilt, so they are not used while the autopilot has "
                "no GNSS of its own; fly it on a nadir gimbal"
            ],
            "yellow",
        )


def _say_what_is_awaited(source: LiveSource, connect: str) -> None:
    """Before the first frame and the autopilot's first message nothing happens: say what the
    companion waits for, so that an empty folder or a silent link does not look like a hang."""
    if isinstance(source, FolderWatch):
        err_console.print(
            escape(
                f"camera: watching {source.folder} for new frames; {source.passed_over} image(s) already "
                "there passed over (taken before this flight, they would place the vehicle where it was)"
            ),
            highlight=False,
            soft_wrap=True,
        )
    err_console.print(
        escape(
            f"autopilot: waiting for its HEARTBEAT and telemetry on {connect}; positions are sent "
            "once it is heard and a frame is fixed"
        ),
        highlight=False,
        soft_wrap=True,
    )
