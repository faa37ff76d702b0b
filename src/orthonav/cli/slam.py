"""``orthonav slam``: one simulated flight of one or two UAVs with a camera rig over an orthophoto,
solved by the SLAM pose graph; trajectory, landmarks, summary and a plot written atomically."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from orthonav.errors import OrthonavError

if TYPE_CHECKING:
    from orthonav.slam import Rig
    from orthonav.slam.simulate import SlamRun, SlamSimConfig, World

console = Console(width=160)


def slam(
    map_tif: Annotated[Path, typer.Option("--map", help="Orthophoto GeoTIFF the map fixes match against.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    frames_from: Annotated[
        Path | None, typer.Option(help="Render the frames from this GeoTIFF (another date; default: --map).")
    ] = None,
    rig_json: Annotated[
        Path | None,
        typer.Option("--rig", help="Rig JSON (docs: File formats, rig JSON); needs a 'nadir' camera."),
    ] = None,
    uavs: Annotated[int, typer.Option(help="1 or 2 UAVs (the second seen by the first's spotter).")] = 1,
    fixes: Annotated[
        bool, typer.Option("--fixes/--no-fixes", help="Map fixes every --fix-every keyframes.")
    ] = True,
    fix_source: Annotated[
        str, typer.Option(help="correlation (dense) or keypoints (ORB against a map of the orthophoto).")
    ] = "correlation",
    fix_every: Annotated[int, typer.Option(help="A map fix is tried every N keyframes.")] = 4,
    keyframes: Annotated[int, typer.Option(help="Keyframes of the flight (8 s apart at 20 m/s).")] = 24,
    seed: Annotated[int, typer.Option(help="Random seed of the flight and the sensors.")] = 0,
) -> None:
    """One simulated SLAM flight: trajectory.jsonl, landmarks.csv, summary.json and slam.png in --out."""
    from orthonav.camera import Camera
    from orthonav.geo import GeoRaster
    from orthonav.localize import orthophoto_fix_source
    from orthonav.slam import Rig
    from orthonav.slam.simulate import NADIR, Setup, SlamSimConfig, default_rig, make_world, run_setup

    if uavs not in (1, 2):
        raise OrthonavError(f"--uavs: expected 1 or 2, got {uavs}")
    for path, option in ((map_tif, "--map"), (frames_from, "--frames-from")):
        if path is not None and not path.is_file():
            raise OrthonavError(f"{option} {path}: no such GeoTIFF")
    rig = (
        _nadir_first(Rig.from_json(rig_json), str(rig_json))
        if rig_json
        else default_rig(Camera.from_hfov(640, 480, 60.0))
    )
    config = SlamSimConfig(keyframes=keyframes, fix_every=fix_every)
    setup = Setup(f"{len(rig)}-camera rig", tuple(rig.names), uavs, fixes)
    with (
        tempfile.TemporaryDirectory(prefix="orthonav-slam-") as tmp,
        GeoRaster(frames_from or map_tif) as frames,
        GeoRaster(map_tif) as map_raster,
    ):
        nadir = rig.cameras[0].camera
        source = (
            orthophoto_fix_source(fix_source, map_raster, nadir, Path(tmp), config.alt_m) if fixes else None
        )
        with console.status(
            f"rendering {keyframes} keyframes x {len(rig)} cameras x {uavs} UAV(s), odometry"
        ):
            world = make_world(frames, rig, config, uavs, seed)
        with console.status(f"SLAM: {setup.label}"):
            run = run_setup(world, setup, source)
    _write_outputs(
        out,
        world,
        run,
        rig,
        config,
        {
            "map": str(map_tif),
            "frames_from": str(frames_from or map_tif),
            "rig": str(rig_json) if rig_json else "built-in (nadir, forward, rear)",
            "seed": seed,
            "fix_source": fix_source if fixes else None,
        },
    )
    summary = json.loads((out / "summary.json").read_text())
    table = Table(
        title=f"SLAM, {setup.label} ({NADIR} + {len(rig) - 1} more), {uavs} UAV(s)", show_header=False
    )
    for key, value in summary["metrics"].items():
        table.add_row(key, str(value))
    table.add_row("fixes used", f"{run.counts['fixes_used']}/{run.counts['fixes_tried']}")
    console.print(table)
    console.print(f"written {out}/trajectory.jsonl, landmarks.csv, summary.json, slam.png")


def _nadir_first(rig: Rig, source: str) -> Rig:
    """The rig with its 'nadir' camera first: odometry, fixes and two-UAV stereo use that one."""
    from orthonav.slam.simulate import NADIR

    if NADIR not in rig.names:
        raise OrthonavError(
            f"{source}: the rig needs a camera named '{NADIR}' (odometry and map fixes use it); "
            f"it has {rig.names}"
        )
    return rig.subset([NADIR, *(n for n in rig.names if n != NADIR)])


def _write_outputs(
    out: Path, world: World, run: SlamRun, rig: Rig, config: SlamSimConfig, inputs: dict
) -> None:
    """Every file through a temporary name, so a reader never sees half of one."""
    from orthonav.atomic import write_json_atomic, write_text_atomic
    from orthonav.slam.simulate import spotting_summary
    from orthonav.viz.slam import plot_slam_run

    out.mkdir(parents=True, exist_ok=True)
    lines = []
    for u, (est, true) in enumerate(zip(run.estimate, run.truth, strict=True)):
        lat, lon = world.frame.to_latlon(est[:, 0], est[:, 1])
        for k in range(len(est)):
            lines.append(
                json.dumps(
                    {
                        "uav": u + 1,
                        "keyframe": k,
                        "t_s": k * config.keyframe_s,
                        "lat": round(float(lat[k]), 8),
                        "lon": round(float(lon[k]), 8),
                        "east_m": round(float(est[k, 0]), 2),
                        "north_m": round(float(est[k, 1]), 2),
                        "alt_m": round(float(est[k, 2]), 2),
                        "yaw_deg": round(float(est[k, 3]), 2),
                        "true_east_m": round(float(true[k, 0]), 2),
                        "true_north_m": round(float(true[k, 1]), 2),
                        "error_m": round(float(np.linalg.norm(est[k, :2] - true[k, :2])), 2),
                    }
                )
            )
    write_text_atomic(out / "trajectory.jsonl", "\n".join(lines) + "\n")
    est, true = run.landmarks_est, run.landmarks_true
    lat, lon = world.frame.to_latlon(est[:, 0], est[:, 1]) if len(est) else (np.zeros(0), np.zeros(0))
    rows = ["east_m,north_m,up_m,lat,lon,true_east_m,true_north_m,error_m"]
    for i in range(len(est)):
        rows.append(
            f"{est[i, 0]:.2f},{est[i, 1]:.2f},{est[i, 2]:.2f},{lat[i]:.8f},{lon[i]:.8f},"
            f"{true[i, 0]:.2f},{true[i, 1]:.2f},{np.linalg.norm(est[i] - true[i]):.2f}"
        )
    write_text_atomic(out / "landmarks.csv", "\n".join(rows) + "\n")
    summary = {
        **inputs,
        "cameras": rig.names,
        "uavs": len(run.estimate),
        "metrics": run.metrics(),
        "wrong_tracks": run.wrong_tracks,
        "counts": run.counts,
        "vo_failures": world.vo_failures,
        "spotting": spotting_summary(world.spotted, config) if world.spotted else None,
        "stereo": run.stereo,
        "config": config.to_dict(),
    }
    write_json_atomic(out / "summary.json", summary)
    title = f"{run.setup.label}: ATE {summary['metrics']['ate_m']} m"
    plot_slam_run(run.estimate, run.truth, est[:, :2], title, out / "slam.png")
