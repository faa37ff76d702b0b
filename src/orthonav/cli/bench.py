"""``orthonav bench``: every benchmark, its table printed and its JSON and PNG written."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table
from tqdm import tqdm

from orthonav.cli.acceptance import bench_acceptance
from orthonav.cli.inputs import (
    DEVICE_HELP,
    SHARED_DATA,
    THREADS_HELP,
    TRUNK_CHECK_HELP,
    weights_conf,
)
from orthonav.cli.output import cell, console, csv_values, print_rows, table_console
from orthonav.errors import OrthonavError
from orthonav.features import Runtime
from orthonav.localize import DEFAULT_COARSE_BACKBONE

if TYPE_CHECKING:
    from orthonav.bench.sitl import SitlConfig

bench_app = typer.Typer(help="Benchmarks (tables printed, JSON written).", no_args_is_help=True)
bench_app.command("acceptance")(bench_acceptance)

_BENCH_COLUMNS = {
    "features": "features",
    "method": "method",
    "condition": "condition",
    "prior": "prior",
    "map": "map",
    "frames_from": "frames",
    "n": "n",
    "fix_rate": "fix",
    "within_5m": "<=5m",
    "within_10m": "<=10m",
    "within_25m": "<=25m",
    "centre_within_10m": "ctr<=10m",
    "centre_within_2px": "ctr<=2px",
    "placed_centre_within_10m": "placed<=10m",
    "median_m": "med m",
    "p95_m": "p95 m",
    "false_25m_rate": ">25m",
    "false_fix_rate": ">50m",
    "within_3sigma": "<=3sig",
    "keypoints": "kp",
    "matches": "matches",
    "inliers": "inl",
    "total_ms": "ms",
}


def height_range(text: str, option: str) -> tuple[float, float]:
    """``LOW,HIGH`` metres, 0 <= LOW <= HIGH, or an error naming the option."""
    values = csv_values(text, option, float)
    if len(values) != 2 or not 0.0 <= values[0] <= values[1] < math.inf:
        raise OrthonavError(f"{option} {text!r}: expected LOW,HIGH in metres with 0 <= LOW <= HIGH")
    return values


def highres_folder(highres: Path | None) -> Path | None:
    """The drone-scale folder to run: None where the shared default is absent, an error where the
    folder asked for is missing (a typo must not quietly drop a third of the benchmark)."""
    if highres is None or highres.is_dir():
        return highres
    if highres == SHARED_DATA / "highres":
        console.print(f"[yellow]note[/]: {highres} absent: the drone-scale orthophotos are left out")
        return None
    raise OrthonavError(
        f"--highres {highres}: no such folder of drone-scale orthophotos (or pass --no-highres)"
    )


@bench_app.command("localize")
def bench_localize(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    highres: Annotated[Path | None, typer.Option(help="Folder of drone-scale orthophotos.")] = (
        SHARED_DATA / "highres"
    ),
    no_highres: Annotated[
        bool, typer.Option("--no-highres", help="Leave the drone-scale orthophotos out.")
    ] = False,
    frames: Annotated[int, typer.Option(help="Frames per condition.")] = 20,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    altitude: Annotated[
        float, typer.Option(help="Altitude AGL (m) of the frames over the NAIP maps.")
    ] = 1000.0,
    highres_altitude: Annotated[
        str, typer.Option(help="Lowest,highest altitude AGL (m) of the frames over the drone-scale maps.")
    ] = "50,150",
    relief: Annotated[
        str,
        typer.Option(
            help="Lowest,highest height (m) of boxes (houses, trees) standing on the drone-scale maps' "
            "ground in their frames, which a flat-ground pose cannot explain; '' renders flat ground."
        ),
    ] = "",
    alt_jitter: Annotated[float, typer.Option(help="Each frame's height varies by this fraction.")] = 0.2,
    max_tilt: Annotated[
        float,
        typer.Option(
            help="Each frame's pitch and roll, uniform within +- this (deg): 25-30 for a body camera."
        ),
    ] = 5.0,
    attitude_noise: Annotated[
        float,
        typer.Option(
            help="Error (deg, 1-sigma) of the roll and pitch the priors carry, which claim 0.3 deg whatever "
            "it is: above that, an autopilot's attitude worse than it says."
        ),
    ] = 0.3,
    prior_radius: Annotated[float, typer.Option(help="How far (m) a prior may be from the truth.")] = 200.0,
    features: Annotated[
        str,
        typer.Option(
            help="Feature backends, comma-separated, run side by side; 'all' = every installed one."
        ),
    ] = "orb",
    fix_sources: Annotated[
        str,
        typer.Option(
            help="Fix sources side by side, comma-separated: keypoints (the localizer), correlation "
            "(dense gradient correlation over the prior's window), cascade (correlation, then "
            "keypoints, verification and calibrated acceptance)."
        ),
    ] = "keypoints",
    coarse_backbone: Annotated[
        str,
        typer.Option(
            help="The cascade's coarse correlations, as fly's --coarse-backbone: gradient, orientation "
            "(the gradients' orientation), trained (the features of orthonav's trained CNN, a ResNet-18 "
            "fitted on aerial photos of several dates), alone or joined by '>' (the second only where "
            "the first rejects the frame)."
        ),
    ] = DEFAULT_COARSE_BACKBONE,
    trunk_check: Annotated[str, typer.Option(help=TRUNK_CHECK_HELP)] = "auto",
    priors: Annotated[
        str,
        typer.Option(
            help="What the frames' priors know, comma-separated: prior (position and heading), "
            "'no heading' (the position alone), 'no position' (the heading alone: lost with a "
            "compass) and 'no prior' (neither); the last two cross-date frames only."
        ),
    ] = "prior,no prior",
    index: Annotated[
        str | None,
        typer.Option(help="A global index on every map (vlad or cnn), for the frames without a prior."),
    ] = None,
    weights: Annotated[
        str | None, typer.Option(help="superpoint's SUPERPOINT.pth,SUPERGLUE.pth (it is skipped without).")
    ] = None,
    speed_sizes: Annotated[
        str, typer.Option(help="Frame widths for the speed table, comma-separated ('' skips it).")
    ] = "320,640,1024",
    device: Annotated[str, typer.Option(help=DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=THREADS_HELP)] = None,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_localize.json"
    ),
) -> None:
    """Cross-date and same-date localization benchmark on real orthophotos."""
    from orthonav.bench import LocalizeBenchConfig, run_localize_benchmark
    from orthonav.bench.localize import CLASSICAL, LOST_MODES, POOLED
    from orthonav.cli.inputs import trunk_check_option
    from orthonav.features import available_backends

    if not data.is_dir():
        raise OrthonavError(f"{data}: no such data folder (pass --data DIR of GeoTIFFs)")
    highres = None if no_highres else highres_folder(highres)
    names = [n for n in available_backends() if n != "superpoint" or weights] if features == "all" else []
    names = names or [n.strip() for n in features.split(",") if n.strip()]
    backend_conf = {"superpoint": weights_conf("superpoint", weights)} if weights else {}
    try:
        sizes = tuple(int(v) for v in speed_sizes.split(",") if v.strip())
    except ValueError:
        raise OrthonavError(
            f"--speed-sizes: expected comma-separated pixel widths, got {speed_sizes!r}"
        ) from None
    config = LocalizeBenchConfig(
        frames=frames,
        seed=seed,
        alt_m=altitude,
        highres_alt_m=height_range(highres_altitude, "--highres-altitude"),
        highres_relief_m=height_range(relief, "--relief") if relief.strip() else None,
        alt_jitter=alt_jitter,
        max_tilt_deg=max_tilt,
        attitude_noise_deg=attitude_noise,
        prior_radius_m=prior_radius,
        features=tuple(names),
        speed_sizes=sizes,
        methods=csv_values(fix_sources, "--fix-sources", str),
        coarse_backbone=coarse_backbone,
        trunk_check=trunk_check_option(trunk_check),
        priors=csv_values(priors, "--priors", str),
        global_index=index,
    )
    learned = sorted(set(config.features) - CLASSICAL)
    if set(LOST_MODES) & set(config.priors) and index is None and learned:
        console.print(
            f"[yellow]note[/]: without --index, the frames without a position search every tile of the map "
            f"by keypoints, seconds a frame for {', '.join(learned)} (a whole run: hours); --index cnn "
            "searches the global index first, --priors prior leaves them out"
        )
    result = run_localize_benchmark(
        data,
        highres,
        out,
        config,
        runtime=Runtime(device, threads),
        backend_conf=backend_conf,
    )
    table = Table(title=f"bench localize ({config.width}x{config.height} frames)", box=None)
    for title in _BENCH_COLUMNS.values():
        table.add_column(title, justify="right")
    for row in result["rows"]:
        table.add_row(*(cell(row.get(key)) for key in _BENCH_COLUMNS))
    table_console.print(table)
    summary = dict(result["summary"])
    targets = summary.pop("targets")
    pooled = Table(title="pooled by backend and condition", box=None)
    columns = ("n", *(c for c in POOLED if c != "centre_within_2px"))
    titles = ("fix", "<=5m", "<=10m", "<=25m", "ctr<=5m", "ctr<=10m", "ctr<=25m", ">25m", ">50m")
    for title in ("backend [method]: condition / prior", "n", *titles, "median ms"):
        pooled.add_column(title, justify="right")
    for key, value in summary.items():
        pooled.add_row(key, *(cell(value[c]) for c in columns), cell(value["median_total_ms"]))
    table_console.print(pooled)
    if config.methods != ("keypoints",):
        keys = dict.fromkeys(k for v in summary.values() for k in v["stage_ms"])
        stages = [
            {"backend [method]: condition / prior": name, **{k: v["stage_ms"].get(k) for k in keys}}
            for name, v in summary.items()
        ]
        print_rows("ms per frame by stage (median)", stages)
    print_rows(
        f"speed over frame sizes (median ms, frame vs 4 tiles; {result['speed']['image']})",
        result["speed"]["rows"],
    )
    for name, ok in targets.items():
        console.print(f"target {name}: {'[green]met[/]' if ok else '[red]not met[/]'}")
    console.print(f"peak RSS {result['peak_rss_mb']} MB; written {out} and {out.with_suffix('.png')}")


@bench_app.command("correction")
def bench_correction(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    neon: Annotated[Path | None, typer.Option(help="Folder of two season folders of plots ('' skips).")] = (
        SHARED_DATA / "neon_sjer"
    ),
    frames: Annotated[int, typer.Option(help="Frames per ordered pair of dates.")] = 8,
    dates: Annotated[str, typer.Option(help="Evaluation dates (never the model's training dates).")] = (
        "20090818,20150926,20200831"
    ),
    backbones: Annotated[str, typer.Option(help="Backbones, comma-separated.")] = (
        "gradient,orientation,trained,vgg11,resnet18,mobilenetv2"
    ),
    sizes: Annotated[str, typer.Option(help="Frame sizes for matching (px).")] = "224,448",
    errors: Annotated[str, typer.Option(help="Initial INS errors (m).")] = "10,15,50,100,200",
    keypoints: Annotated[
        str, typer.Option(help="Keypoint backends for comparison ('' skips).")
    ] = "orb,aliked",
    model: Annotated[Path | None, typer.Option(help="Model file for 'trained' (default: shipped).")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    threads: Annotated[int | None, typer.Option(help=THREADS_HELP)] = None,
    out: Annotated[Path, typer.Option(help="JSON output (PNGs are written beside it).")] = Path(
        "runs/bench_correction.json"
    ),
) -> None:
    """INS correction by dense correlation on real cross-date imagery, every backbone side by side."""
    from orthonav.bench.correction import CorrectionBenchConfig, run_correction_benchmark

    if not data.is_dir():
        raise OrthonavError(f"{data}: no such data folder (pass --data DIR of GeoTIFFs)")
    if threads:
        import torch

        torch.set_num_threads(threads)
    config = CorrectionBenchConfig(
        frames=frames,
        seed=seed,
        eval_dates=csv_values(dates, "--dates"),
        backbones=csv_values(backbones, "--backbones"),
        sizes=csv_values(sizes, "--sizes", int),
        initial_errors_m=csv_values(errors, "--errors", float),
        keypoint_features=tuple(k.strip() for k in keypoints.split(",") if k.strip()),
        model_path=str(model) if model else None,
    )
    result = run_correction_benchmark(data, neon if neon and neon.is_dir() else None, out, config)
    print_rows("correction vs keypoints, NAIP cross-date (errors in m, rates of all frames)", result["rows"])
    print_rows("time per correction (median ms)", result["speed"])
    route = result["route"]
    print_rows(
        f"route {route['frames']} frames over {route['map']} map",
        [{"track": k, **v} for k, v in route["stats"].items()],
    )
    if result["neon"]:
        print_rows(f"NEON cross-season, {result['neon']['plots']} plots (m)", result["neon"]["rows"])
    for name, ok in result["targets"].items():
        console.print(f"target {name}: {'[green]met[/]' if ok else '[red]not met[/]'}")
    console.print(f"written {out}, {out.with_suffix('.png')} and {out.with_name(out.stem + '_route.png')}")


@bench_app.command("mission")
def bench_mission(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    map_date: Annotated[str, typer.Option(help="The map's GeoTIFF: a unique part of its name.")] = "2018",
    frames_date: Annotated[str, typer.Option(help="The frames' GeoTIFF (another date).")] = "2020",
    missions: Annotated[int, typer.Option(help="Missions per backend.")] = 30,
    features: Annotated[
        str,
        typer.Option(
            help="Fix sources side by side, comma-separated: keypoint backends (orb, sift, aliked, ...), "
            "correlation, cascade."
        ),
    ] = "orb",
    imu: Annotated[str, typer.Option(help="IMU error model: perfect, tactical, consumer.")] = "consumer",
    altitude: Annotated[float, typer.Option(help="Altitude AGL (m).")] = 1000.0,
    min_leg: Annotated[float, typer.Option(help="Least start-to-target distance (m).")] = 1500.0,
    latency_s: Annotated[
        float, typer.Option(help="Seconds of companion mode (sim vehicle over UDP) for the latency; 0 skips.")
    ] = 30.0,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    device: Annotated[str, typer.Option(help=DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=THREADS_HELP)] = None,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG and the runs are written beside it).")] = Path(
        "runs/bench_mission.json"
    ),
) -> None:
    """Navigation missions: N per backend, GNSS lost, INS drifting, visual fixes fused."""
    from orthonav.bench.mission import MissionBenchConfig, run_mission_benchmark

    config = MissionBenchConfig(
        missions=missions,
        features=csv_values(features, "--features"),
        seed=seed,
        imu=imu,
        alt_m=altitude,
        min_leg_m=min_leg,
        latency_s=latency_s,
    )
    map_tif, frames_tif = _dated(data, map_date, "--map-date"), _dated(data, frames_date, "--frames-date")
    result = run_mission_benchmark(map_tif, frames_tif, out, config, runtime=Runtime(device, threads))
    print_rows(
        f"{missions} missions per backend, map {map_tif.stem}, frames {frames_tif.stem}, {imu} IMU",
        [{"features": k, **v} for k, v in result["summary"].items()],
    )
    print_rows("companion mode over UDP: frame capture -> MAVLink message (ms)", result["latency"])
    console.print(f"written {out} and {out.with_suffix('.png')}; runs in {out.with_suffix('')}")


@bench_app.command("relocalize")
def bench_relocalize(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    blocks: Annotated[
        str, typer.Option(help="Mosaic sizes in blocks (a quarter of one date each), comma-separated.")
    ] = "2,6,12,24",
    frames: Annotated[int, typer.Option(help="Lost frames per map size and condition.")] = 20,
    features: Annotated[str, typer.Option(help="Feature backend of the maps.")] = "orb",
    altitude: Annotated[float, typer.Option(help="Altitude AGL (m).")] = 1000.0,
    words: Annotated[int, typer.Option(help="Vocabulary size of the index.")] = 32,
    index: Annotated[
        str, typer.Option(help="Global index methods side by side, comma-separated: vlad, cnn.")
    ] = "vlad",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    all_tiles: Annotated[
        bool, typer.Option("--all-tiles/--index-only", help="Also match every tile, for comparison.")
    ] = True,
    fix_sources: Annotated[
        str,
        typer.Option(
            help="Fix sources side by side, comma-separated: keypoints (the localizer), correlation "
            "(dense gradient correlation around the index's top tiles), cascade (fly's default)."
        ),
    ] = "keypoints",
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_relocalize.json"
    ),
) -> None:
    """Lost frames on growing maps: global index recall, fixes and time vs matching every tile."""
    from orthonav.bench.relocalize import RelocalizeBenchConfig, run_relocalize_benchmark

    sources = _sources(data)
    config = RelocalizeBenchConfig(
        blocks=csv_values(blocks, "--blocks", int),
        frames=frames,
        alt_m=altitude,
        features=features,
        words=words,
        indexes=csv_values(index, "--index", str),
        seed=seed,
        all_tiles=all_tiles,
        fix_sources=csv_values(fix_sources, "--fix-sources", str),
    )
    result = run_relocalize_benchmark(sources, out, config)
    title = f"lost frames ({features}, {altitude:g} m): index top {config.candidates} vs every tile"
    print_rows(title, result["rows"])
    console.print(f"written {out} and {out.with_suffix('.png')}")


@bench_app.command("mapbuild")
def bench_mapbuild(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    blocks: Annotated[str, typer.Option(help="Mosaic sizes in blocks (4.2 km² each), comma-separated.")] = (
        "6,24,96,192"
    ),
    workers: Annotated[
        str, typer.Option(help="Worker counts, comma-separated (0: single process).")
    ] = "0,1,2",
    altitude: Annotated[float, typer.Option(help="Nominal altitude of the maps (m).")] = 1000.0,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_mapbuild.json"
    ),
) -> None:
    """Map build throughput and peak memory by map size, single process and on Dask."""
    from orthonav.bench.mapbuild import MapBuildBenchConfig, run_mapbuild_benchmark

    config = MapBuildBenchConfig(
        blocks=csv_values(blocks, "--blocks", int),
        workers=csv_values(workers, "--workers", int),
        alt_m=altitude,
    )
    result = run_mapbuild_benchmark(_sources(data), out, config)
    print_rows("map build (ORB): throughput and peak memory", result["rows"])
    console.print(f"written {out} and {out.with_suffix('.png')}")


@bench_app.command("slam")
def bench_slam(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    map_date: Annotated[str, typer.Option(help="The map GeoTIFF of the fixes: part of its name.")] = "2018",
    frames_date: Annotated[str, typer.Option(help="The frames' GeoTIFF (another date).")] = "2020",
    seeds: Annotated[int, typer.Option(help="Worlds (flights) per setup; medians are over them.")] = 3,
    keyframes: Annotated[int, typer.Option(help="Keyframes per flight (8 s apart at 20 m/s).")] = 24,
    fix_source: Annotated[
        str, typer.Option(help="Map fixes: correlation (dense) or keypoints (ORB against a map).")
    ] = "correlation",
    fix_every: Annotated[int, typer.Option(help="A map fix is tried every N keyframes.")] = 4,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_slam.json"
    ),
) -> None:
    """SLAM: VO alone, one camera, a nadir+oblique rig, two UAVs; each without and with map fixes."""
    from orthonav.bench.slam import SlamBenchConfig, run_slam_benchmark
    from orthonav.slam.simulate import SlamSimConfig

    config = SlamBenchConfig(
        seeds=seeds, fix_source=fix_source, sim=SlamSimConfig(keyframes=keyframes, fix_every=fix_every)
    )
    map_tif, frames_tif = _dated(data, map_date, "--map-date"), _dated(data, frames_date, "--frames-date")
    result = run_slam_benchmark(map_tif, frames_tif, out, config)
    print_rows(
        f"SLAM over {frames_tif.stem}, fixes: {fix_source} on {map_tif.stem} (medians of {seeds})",
        result["summary"],
    )
    stereo = result["stereo"]["median"]
    if stereo:
        print_rows(
            "two-UAV stereo, baseline from the other UAV's known size (medians)",
            [
                {"baseline": k, "distance error (m)": v, "size error (%)": stereo["size_error_pct"][k]}
                for k, v in stereo["distance_error_m"].items()
            ],
        )
    console.print(f"written {out} and {out.with_suffix('.png')}")


def _sources(data: Path) -> list[Path]:
    """Every GeoTIFF of a data folder (the dates of one area)."""
    sources = sorted(data.glob("*.tif")) if data.is_dir() else []
    if not sources:
        raise OrthonavError(f"{data}: no GeoTIFFs (pass --data DIR of one area's dates)")
    return sources


def _dated(data: Path, part: str, option: str) -> Path:
    """The one GeoTIFF in ``data`` whose name contains ``part``."""
    if not data.is_dir():
        raise OrthonavError(f"{data}: no such data folder (pass --data DIR of GeoTIFFs)")
    found = [p for p in sorted(data.glob("*.tif")) if part in p.name]
    if len(found) != 1:
        names = ", ".join(p.name for p in sorted(data.glob("*.tif"))) or "none"
        raise OrthonavError(
            f"{option} {part!r}: expected exactly one GeoTIFF in {data} to match; has {names}"
        )
    return found[0]


@bench_app.command("odometry")
def bench_odometry(
    photos: Annotated[Path, typer.Option(help="Folder of geotagged drone photos.")] = SHARED_DATA
    / "brighton_beach"
    / "images",
    features: Annotated[
        str, typer.Option(help="Feature backends, comma-separated, side by side.")
    ] = "orb,sift",
    methods: Annotated[str, typer.Option(help="Motion models, comma-separated.")] = "homography,essential",
    max_side: Annotated[int, typer.Option(help="Frames are shrunk to this longest side (px).")] = 1280,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_odometry.json"
    ),
) -> None:
    """Frame-to-frame VO on real drone photos: displacement (m) and heading-change (deg) errors."""
    from orthonav.bench.odometry import OdometryBenchConfig, run_odometry_benchmark

    config = OdometryBenchConfig(
        csv_values(features, "--features"), csv_values(methods, "--methods"), max_side
    )
    result = run_odometry_benchmark(photos, out, config)
    print_rows(f"VO on {result['pairs']} photo pairs vs GNSS / recorded heading", result["summary"])
    console.print(f"written {out} and {out.with_suffix('.png')}")


@bench_app.command("robustness")
def bench_robustness(
    naip: Annotated[Path, typer.Option(help="Folder of NAIP GeoTIFFs ('' skips).")] = SHARED_DATA / "naip",
    photos: Annotated[Path, typer.Option(help="Folder of drone photos ('' skips).")] = (
        SHARED_DATA / "brighton_beach" / "images"
    ),
    width: Annotated[int, typer.Option(help="Images are resized to this width (px).")] = 800,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_robustness.json"
    ),
) -> None:
    """Repeatability of points (ORB, SIFT, low-level key objects) vs line segments under change."""
    from orthonav.bench.robustness import RobustnessBenchConfig, run_robustness_benchmark

    result = run_robustness_benchmark(naip, photos, out, RobustnessBenchConfig(width_px=width))
    print_rows("repeatability, mean over levels (lines vs points in %)", result["lines_vs_points"])
    console.print(f"median detections per image: {result['median_count']}")
    console.print(f"written {out} and {out.with_suffix('.png')}")


@bench_app.command("real")
def bench_real(
    dataset: Annotated[
        Path, typer.Argument(help="Folder laid out like ../shared/data/real/seneca (ortho, dsm, queries).")
    ] = SHARED_DATA / "real" / "seneca",
    features: Annotated[str, typer.Option(help="Feature backends, comma-separated, side by side.")] = "orb",
    fix_sources: Annotated[
        str, typer.Option(help="Among keypoints, cascade (fly's default), correlation; comma-separated.")
    ] = "keypoints",
    variants: Annotated[
        str, typer.Option(help="flat|dsm, each with or without +att (the attitude prior), comma-separated.")
    ] = "flat,flat+att,dsm,dsm+att",
    prior_sigma: Annotated[float, typer.Option(help="1-sigma of the EXIF position prior (m).")] = 10.0,
    attitude_noise: Annotated[
        float, typer.Option(help="Noise of the roll/pitch prior (deg, 1-sigma).")
    ] = 1.0,
    flip_attitude: Annotated[
        bool, typer.Option(help="Give roll and pitch with the wrong sign (a misconfigured autopilot).")
    ] = False,
    limit: Annotated[int | None, typer.Option(help="The first N photos only.")] = None,
    seed: Annotated[int, typer.Option(help="Random seed of the prior noise.")] = 0,
    max_frame_px: Annotated[
        int | None,
        typer.Option(
            help="The maps' frame size budget (map build --max-frame-px; default: each backend's, "
            "512 for aliked and disk, 800 for the others); each its own map."
        ),
    ] = None,
    coarse_backbone: Annotated[
        str, typer.Option(help="The cascade's coarse correlations, as fly's --coarse-backbone.")
    ] = DEFAULT_COARSE_BACKBONE,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_real.json"
    ),
) -> None:
    """Real drone photos against a true orthophoto (and DSM): fixes, errors vs the reference, sigma."""
    from orthonav.bench.real import RealBenchConfig, run_real_benchmark, tail_rows

    config = RealBenchConfig(
        features=csv_values(features, "--features"),
        fix_sources=csv_values(fix_sources, "--fix-sources"),
        variants=csv_values(variants, "--variants"),
        prior_sigma_m=prior_sigma,
        attitude_noise_deg=attitude_noise,
        attitude_sign=-1.0 if flip_attitude else 1.0,
        limit=limit,
        seed=seed,
        max_frame_px=max_frame_px,
        coarse_backbone=coarse_backbone,
    )
    if not dataset.is_dir():
        raise OrthonavError(
            f"{dataset}: no such dataset folder (pass DATASET, a folder laid out like "
            "../shared/data/real/seneca; the default is relative to where the command runs)"
        )
    with tqdm(desc="bench real", unit="photo") as bar:

        def step(what: str, total: int) -> None:
            bar.total = total
            bar.set_postfix_str(what)
            bar.update()

        result = run_real_benchmark(dataset, out, config, step)
    columns = ("features", "fix_source", "variant", "fixed", "within_1m", "within_3m", "within_10m")
    columns += ("placed_within_3m", "median_m", "p90_m")
    columns += ("false_fixes", "within_3sigma", "mean_nees", "median_sigma_m", "total_ms", "mean_total_ms")
    print_rows(
        f"real photos: {result['photos']} of {dataset.name}, errors vs the reference camera position",
        [{k: r.get(k) for k in columns} for r in result["rows"]],
    )
    print_rows("ms per stage over the photos: p50, p95, p99, max", tail_rows(result))
    for name, ok in result["targets"].items():
        console.print(f"target {name}: {'[green]met[/]' if ok else '[red]not met[/]'}")
    console.print(f"written {out}")


@bench_app.command("runtime")
def bench_runtime(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    frames: Annotated[int, typer.Option(help="Frames (rendered at known poses).")] = 8,
    sizes: Annotated[str, typer.Option(help="Correction sizes (px).")] = "224,448",
    repeats: Annotated[int, typer.Option(help="Timed runs of each frame after a warm-up.")] = 5,
    runtimes: Annotated[str, typer.Option(help="Among torch, onnx-fp32, onnx-int8.")] = (
        "torch,onnx-fp32,onnx-int8"
    ),
    threads: Annotated[
        int | None, typer.Option(help="Threads for torch and ONNX Runtime (default: one per physical core).")
    ] = None,
    parts: Annotated[
        str, typer.Option(help="What to time, among corrections, index, xfeat (extraction), comma-separated.")
    ] = "corrections,index,xfeat",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_runtime.json"
    ),
) -> None:
    """The trained correction, the index descriptor and XFeat under torch vs ONNX Runtime."""
    from orthonav.bench.runtime import RuntimeBenchConfig, run_runtime_benchmark

    if not data.is_dir():
        raise OrthonavError(f"{data}: no such data folder (pass --data DIR of GeoTIFFs)")
    config = RuntimeBenchConfig(
        frames=frames,
        sizes=csv_values(sizes, "--sizes", int),
        repeats=repeats,
        runtimes=csv_values(runtimes, "--runtimes"),
        threads=threads,
        parts=csv_values(parts, "--parts"),
        seed=seed,
    )
    result = run_runtime_benchmark(data, out, config)
    machine = result["machine"]
    load = machine["load_avg_before"][0]
    title = f"time per correction and accuracy ({machine['threads']} threads, load {load})"
    print_rows(title, result.get("corrections", []))
    print_rows("time per index descriptor", result.get("index", []))
    print_rows("XFeat extraction per frame (median ms) and agreement with torch", result.get("xfeat", []))
    console.print(f"written {out} and {out.with_suffix('.png')}")


@bench_app.command("speed")
def bench_speed(
    data: Annotated[Path, typer.Option(help="Folder of co-registered NAIP GeoTIFFs (dates).")] = (
        SHARED_DATA / "naip"
    ),
    real: Annotated[
        Path | None,
        typer.Option(help="Real-photo dataset (like ../shared/data/real/seneca); --photos 0 skips it."),
    ] = SHARED_DATA / "real" / "seneca",
    features: Annotated[str, typer.Option(help="Feature backends, comma-separated.")] = "orb,aliked",
    engines: Annotated[
        str,
        typer.Option(
            help="Engines of the learned backends: torch, onnx (where a backend has one), onnx-int8 "
            "(its int8 graph, where it has one: aliked), cuda (torch, GPU)."
        ),
    ] = "torch,onnx,onnx-int8",
    fix_sources: Annotated[
        str,
        typer.Option(help="keypoints (the backend alone), cascade (as the cascade's fine stage), or both."),
    ] = "keypoints",
    coarse_backbones: Annotated[
        str,
        typer.Option(
            help="The cascade's coarse correlations, comma-separated, each a run of its own (fly's "
            "--coarse-backbone: e.g. gradient,gradient>orientation)."
        ),
    ] = DEFAULT_COARSE_BACKBONE,
    frames: Annotated[int, typer.Option(help="NAIP frames per condition (same-date, cross-date).")] = 8,
    photos: Annotated[int, typer.Option(help="Real photos, spread over the flight.")] = 12,
    map_year: Annotated[
        str, typer.Option(help="The NAIP GeoTIFF of the map: a unique part of its name.")
    ] = "2020",
    frames_year: Annotated[
        str, typer.Option(help="The NAIP GeoTIFF of the cross-date frames: a unique part of its name.")
    ] = "2015",
    latency_s: Annotated[
        float, typer.Option(help="Seconds of companion loop (sim vehicle over UDP) per run; 0 skips it.")
    ] = 0.0,
    latency_frames: Annotated[
        str,
        typer.Option(
            help="The loop's frames: same-date (the map's orthophoto: every backend fixes) or cross-date "
            "(--frames-year's: the latency where frames are rejected and a chain asks its later cascades)."
        ),
    ] = "same-date",
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    max_frame_px: Annotated[
        int | None,
        typer.Option(
            help="The photos' map frame size budget (map build --max-frame-px; default: the backend's)."
        ),
    ] = None,
    baseline: Annotated[
        bool,
        typer.Option(
            help="Beside ORB, the plain ORB tile loop (ratio test, RANSAC homography, no checks) on the "
            "same NAIP frames: the reference row."
        ),
    ] = True,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_speed.json"
    ),
) -> None:
    """Every backend on every engine it has, side by side: ms per stage, fps, peak memory, accuracy."""
    from orthonav.bench.machine import machine_line
    from orthonav.bench.speed import SpeedBenchConfig, run_speed_benchmark, table_rows, tail_rows

    if not data.is_dir():
        raise OrthonavError(f"{data}: no such data folder (pass --data DIR of GeoTIFFs)")
    config = SpeedBenchConfig(
        features=csv_values(features, "--features"),
        engines=csv_values(engines, "--engines"),
        fix_sources=csv_values(fix_sources, "--fix-sources"),
        coarse_backbones=csv_values(coarse_backbones, "--coarse-backbones"),
        frames=frames,
        photos=photos,
        map_year=map_year,
        frames_year=frames_year,
        latency_s=latency_s,
        latency_frames=latency_frames,
        seed=seed,
        max_frame_px=max_frame_px,
        baseline=baseline,
    )
    real_dir = real if photos and real is not None else None
    if real_dir is not None and not real_dir.is_dir():
        raise OrthonavError(f"{real_dir}: no such real-photo dataset (pass --real DIR, or --photos 0)")
    result = run_speed_benchmark(
        data, real_dir, out, config, progress=lambda what: console.print(f"... {what}")
    )
    print_rows("median ms per frame, accuracy and peak memory, per backend and engine", table_rows(result))
    print_rows("ms per stage over the frames: p50, p95, p99, max", tail_rows(result))
    console.print(machine_line(result["machine"]))
    runs = len(result["rows"])
    console.print(f"{runs} runs side by side; written {out} and {out.with_suffix('.png')}")


@bench_app.command("faults")
def bench_faults(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    frames_date: Annotated[
        str, typer.Option(help="The GeoTIFF the camera frames are rendered from: a unique part of its name.")
    ] = "2020",
    map_dir: Annotated[
        Path | None,
        typer.Option("--map", help="Map package fly uses; default: built once from the frames' GeoTIFF."),
    ] = None,
    scenarios: Annotated[
        str, typer.Option(help="Scenarios, comma-separated (default: all; see the docs for the list).")
    ] = "",
    parallel: Annotated[int, typer.Option(help="Scenarios flown at once (each is two processes).")] = 3,
    fault_at: Annotated[float, typer.Option(help="Seconds of normal flight before the fault.")] = 10.0,
    fault_duration: Annotated[float, typer.Option(help="Seconds the fault lasts.")] = 6.0,
    seed: Annotated[int, typer.Option(help="Random seed (corruption, the vehicle's sensors).")] = 0,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG and each scenario's logs beside it).")] = Path(
        "runs/bench_faults.json"
    ),
) -> None:
    """The real fly and sim-vehicle processes through faults: wrong positions sent, time to recover."""
    from orthonav.bench.faults import FaultBenchConfig, ensure_map, run_fault_benchmark, summary_line

    config = FaultBenchConfig(
        scenarios=csv_values(scenarios, "--scenarios") if scenarios else (),
        parallel=parallel,
        fault_at_s=fault_at,
        fault_s=fault_duration,
        seed=seed,
    )
    frames_from = _dated(data, frames_date, "--frames-date")
    package = map_dir or ensure_map(frames_from, out.with_suffix("") / "map", config.alt_m)
    result = run_fault_benchmark(package, frames_from, out, config)
    columns = ("scenario", "positions", "wrong", "wrong_in_fault", "unverifiable", "leaked")
    columns += ("median_error_m", "max_error_m", "autopilot_back_s", "resumed_s", "fixes_fused", "passed")
    print_rows(
        f"fault injection: fly + sim-vehicle, fault at {fault_at:g} s for {fault_duration:g} s",
        [{k: r.get(k) for k in columns} for r in result["rows"]],
    )
    console.print(summary_line(result))
    console.print(f"written {out} and {out.with_suffix('.png')}; logs in {out.with_suffix('')}")


@bench_app.command("sitl")
def bench_sitl(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    map_date: Annotated[
        str, typer.Option(help="The GeoTIFF the map is built from: a unique part of its name.")
    ] = ("2018"),
    frames_date: Annotated[
        str, typer.Option(help="The GeoTIFF the camera frames are rendered from (another year).")
    ] = "2020",
    sitl_dir: Annotated[
        Path, typer.Option(help="Folder with ArduPilot's SITL binaries (arducopter) and their .parm files.")
    ] = SHARED_DATA.parent / "ardupilot",
    scenarios: Annotated[
        str,
        typer.Option(
            help="Flights, comma-separated (default: copter-gnss-off-velocity, the copter with fly's "
            "defaults for a gimbal camera, and its twin without orthonav)."
        ),
    ] = "",
    altitude: Annotated[float, typer.Option(help="Cruise altitude above home (m).")] = 300.0,
    hfov: Annotated[
        float, typer.Option(help="The camera's horizontal field of view (deg): the frames' and the map's.")
    ] = 60.0,
    param: Annotated[
        list[str] | None,
        typer.Option(
            help="An ArduPilot parameter set over every scenario's, NAME=VALUE (repeat for more): an "
            "experiment, recorded in the result's config and rows."
        ),
    ] = None,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG and each flight's logs beside it).")] = Path(
        "runs/bench_sitl.json"
    ),
) -> None:
    """ArduPilot's real firmware (SITL, EKF3) flies an AUTO mission with GNSS cut in flight and
    orthonav as its second GPS; the same mission without orthonav beside it. Real time: minutes."""
    from orthonav.bench.sitl import (
        DEFAULT_SCENARIOS,
        SitlConfig,
        extra_param,
        run_sitl_benchmark,
        summary_line,
    )

    names = csv_values(scenarios, "--scenarios") if scenarios else DEFAULT_SCENARIOS
    extra = tuple(extra_param(text) for text in param or ())
    config = SitlConfig(scenarios=tuple(names), alt_m=altitude, hfov_deg=hfov, extra_params=extra)
    map_from, frames_from, package = _sitl_inputs(data, map_date, frames_date, out, config)
    result = run_sitl_benchmark(sitl_dir, package, frames_from, out, config)
    columns = (
        "name",
        "orthonav",
        "completed",
        "gnss_off_s",
        "horizontal_error_p50_m",
        "horizontal_error_p95_m",
    )
    columns += ("horizontal_error_max_m", "landing_error_m", "targets_met")
    title = f"ArduPilot SITL: map {map_from.stem}, frames {frames_from.stem}"
    _print_sitl(title, result, columns, summary_line(result), out)


@bench_app.command("sitl-faults")
def bench_sitl_faults(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    map_date: Annotated[str, typer.Option(help="The GeoTIFF the map is built from.")] = "2018",
    frames_date: Annotated[
        str, typer.Option(help="The GeoTIFF the camera frames are rendered from.")
    ] = "2020",
    sitl_dir: Annotated[
        Path, typer.Option(help="Folder with ArduPilot's SITL binaries and their .parm files.")
    ] = SHARED_DATA.parent / "ardupilot",
    faults: Annotated[str, typer.Option(help="Fault flights, comma-separated (default: all).")] = "",
    altitude: Annotated[float, typer.Option(help="Cruise altitude above home (m).")] = 300.0,
    hfov: Annotated[float, typer.Option(help="The camera's horizontal field of view (deg).")] = 90.0,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG and each flight's logs beside it).")] = Path(
        "runs/bench_sitl_faults.json"
    ),
) -> None:
    """Link loss, a camera stall, an autopilot reboot and a steep bank, each in its own flight of
    ArduPilot's real firmware (SITL) with orthonav as GPS 2. Real time: minutes a flight."""
    from orthonav.bench.sitl import SitlConfig
    from orthonav.bench.sitl_faults import FAULTS, run_sitl_fault_benchmark, summary_line

    names = tuple(csv_values(faults, "--faults")) if faults else tuple(FAULTS)
    config = SitlConfig(alt_m=altitude, hfov_deg=hfov)
    map_from, frames_from, package = _sitl_inputs(data, map_date, frames_date, out, config)
    result = run_sitl_fault_benchmark(names, sitl_dir, package, frames_from, out, config)
    columns = ("name", "fault", "completed", "fault_window_s", "resumed_s", "fixes_in_fault", "passed")
    title = f"ArduPilot SITL faults: map {map_from.stem}, frames {frames_from.stem}"
    _print_sitl(title, result, columns, summary_line(result), out)


def _sitl_inputs(
    data: Path, map_date: str, frames_date: str, out: Path, config: SitlConfig
) -> tuple[Path, Path, Path]:
    """The map's and the frames' GeoTIFFs, and the map package for the camera and the cruise
    altitude, built beside ``out`` once (a SITL flight must not wait for it)."""
    from orthonav.bench.faults import ensure_map

    map_from = _dated(data, map_date, "--map-date")
    frames_from = _dated(data, frames_date, "--frames-date")
    name = f"map_{map_from.stem}_{config.alt_m:g}m_{config.hfov_deg:g}deg"
    return (
        map_from,
        frames_from,
        ensure_map(map_from, out.with_suffix("") / name, config.alt_m, config.hfov_deg),
    )


def _print_sitl(title: str, result: dict, columns: tuple[str, ...], summary: str, out: Path) -> None:
    """The flights' table, the one-line summary and where the files went."""
    rows = [{k: r.get(k) for k in columns} for r in result["rows"]]
    print_rows(f"{title}, {result['config']['alt_m']:g} m", rows)
    console.print(summary)
    console.print(f"written {out} and {out.with_suffix('.png')}; logs in {out.with_suffix('')}")
