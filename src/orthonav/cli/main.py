"""``orthonav``: map build/info, localize, simulate, demo, bench."""

from __future__ import annotations

import json
import logging
import sys
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from orthonav.camera import Camera
from orthonav.cli.correction import correction_app
from orthonav.cli.fly import fly
from orthonav.cli.inputs import camera_from_options, parse_latlon, parse_length_m, read_priors, weights_conf
from orthonav.cli.odometry import bench_odometry, bench_robustness, odometry
from orthonav.cli.replay import replay
from orthonav.cli.serve import serve
from orthonav.cli.slam import slam
from orthonav.cli.vehicle import sim_vehicle
from orthonav.errors import OrthonavError
from orthonav.features import Runtime
from orthonav.frames import list_images

app = typer.Typer(
    help="Map-based optical navigation for drones without GNSS.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
map_app = typer.Typer(help="Build and inspect map packages.", no_args_is_help=True)
bench_app = typer.Typer(help="Benchmarks (tables printed, JSON written).", no_args_is_help=True)
app.add_typer(map_app, name="map")
app.add_typer(bench_app, name="bench")
app.add_typer(correction_app, name="correction")
app.command()(fly)
app.command("sim-vehicle")(sim_vehicle)
app.command()(replay)
app.command()(serve)
app.command()(slam)
app.command()(odometry)
bench_app.command("odometry")(bench_odometry)
bench_app.command("robustness")(bench_robustness)
console = Console()
err_console = Console(stderr=True)
# Tables stay readable when piped to a file (rich would wrap them at 80 columns).
table_console = console if console.is_terminal else Console(width=160)


def main() -> None:
    """Console entry point: user errors become one clear line and exit code 2."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        app()
    except OrthonavError as exc:
        # One line whatever the terminal width; the message is text, not rich markup.
        err_console.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        err_console.print("interrupted: results written so far are kept (a map build resumes when rerun)")
        sys.exit(130)


_WEIGHTS_HELP = "Weight files for backends that take them (superpoint: SUPERPOINT.pth,SUPERGLUE.pth)."
_DEVICE_HELP = "Where learned backends run: cpu, cuda or cuda:N."
_THREADS_HELP = "Torch CPU threads for learned backends (default: torch's choice)."


def _print_dict(title: str, data: dict) -> None:
    table = Table(title=title, show_header=False)
    for key, value in data.items():
        table.add_row(str(key), str(value))
    table_console.print(table)


@map_app.command("build")
def map_build(
    ortho: Annotated[
        Path,
        typer.Argument(help="GeoTIFF/COG orthophoto (any CRS), a VRT, or a folder of GeoTIFFs to mosaic."),
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Map package directory to write.")],
    camera_json: Annotated[Path | None, typer.Option("--camera", help="Camera JSON.")] = None,
    crs: Annotated[
        str | None,
        typer.Option(help="CRS of a folder's mosaic (default: the first file's), e.g. EPSG:32614."),
    ] = None,
    width: Annotated[int, typer.Option(help="Frame width (px) without --camera.")] = 640,
    height: Annotated[int, typer.Option(help="Frame height (px) without --camera.")] = 480,
    hfov: Annotated[float, typer.Option(help="Horizontal field of view (deg) without --camera.")] = 60.0,
    altitude: Annotated[float, typer.Option(help="Nominal flight altitude above ground (m).")] = 300.0,
    scale_coef: Annotated[float, typer.Option(help="Tile size = footprint x this.")] = 1.5,
    overlap: Annotated[float, typer.Option(help="Tile overlap fraction.")] = 0.5,
    features: Annotated[str, typer.Option(help="Feature backend (see README: Feature backends).")] = "orb",
    max_keypoints: Annotated[int, typer.Option(help="Keypoints per tile.")] = 1024,
    weights: Annotated[str | None, typer.Option(help=_WEIGHTS_HELP)] = None,
    device: Annotated[str, typer.Option(help=_DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP)] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing package.")] = False,
    workers: Annotated[
        int | None,
        typer.Option(help="Build on a local Dask cluster of N worker processes (needs orthonav[scale])."),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Build on an existing Dask cluster at this scheduler address (tcp://HOST:PORT); "
            "its workers must see the orthophoto and the output folder at the same paths."
        ),
    ] = None,
) -> None:
    """Tile an orthophoto and extract features into a map package (resumable, atomic)."""
    from orthonav.geo.mosaic import build_vrt, mosaic_sources
    from orthonav.mapdb import TilingConfig, build_map

    start = time.perf_counter()
    if ortho.is_dir():
        # The mosaic (and any reprojected copies) lives beside the package, which refers to it.
        ortho = build_vrt(mosaic_sources(ortho), out.with_name(out.name + ".mosaic") / "mosaic.vrt", crs)
    elif crs:
        raise OrthonavError(f"--crs {crs}: applies to a folder of GeoTIFFs; {ortho} is one file")
    package = build_map(
        ortho,
        out,
        camera_from_options(camera_json, width, height, hfov),
        TilingConfig(altitude, scale_coef, overlap),
        features,
        {"max_keypoints": max_keypoints, **weights_conf(features, weights)},
        overwrite=overwrite,
        runtime=Runtime(device, threads),
        workers=workers,
        scheduler=scheduler,
    )
    elapsed_s = time.perf_counter() - start
    _print_dict(f"map package {out}", package.summary())
    console.print(f"{len(package)} tiles in {elapsed_s:.1f} s ({len(package) / elapsed_s:.1f} tiles/s)")


@map_app.command("info")
def map_info(
    map_dir: Annotated[Path, typer.Argument(help="Map package directory.")],
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
) -> None:
    """Summarise a map package."""
    from orthonav.mapdb import MapPackage

    summary = MapPackage(map_dir).summary()
    if as_json:
        print(json.dumps(summary, indent=2))
    else:
        _print_dict(f"map package {map_dir}", summary)


@map_app.command("index")
def map_index(
    map_dir: Annotated[Path, typer.Argument(help="Map package directory.")],
    words: Annotated[int, typer.Option(help="Vocabulary size (k-means words) of the VLAD descriptors.")] = 32,
    seed: Annotated[int, typer.Option(help="Random seed of the k-means.")] = 0,
    method: Annotated[
        str, typer.Option(help="vlad (the map's own local features) or cnn (trained, robust across dates).")
    ] = "vlad",
    model: Annotated[
        Path | None, typer.Option(help="cnn: a retrieval model file (default: the one shipped).")
    ] = None,
) -> None:
    """Add a global re-localization index: a lost frame is matched to its top tiles, not to all."""
    from orthonav.mapdb import MapPackage, build_global_index

    package = build_global_index(MapPackage(map_dir), words, seed, method, model, progress=True)
    what = f"{words} words" if method == "vlad" else f"model {package.global_index.model}"
    console.print(f"global index ({method}): {len(package)} tiles, {what} -> {map_dir / 'global.npz'}")


@map_app.command("train-index")
def map_train_index(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")],
    dates: Annotated[
        str, typer.Option(help="Training dates (substrings of the file names), comma-separated.")
    ] = "20090818,20120731,20150926,20180716",
    out: Annotated[Path, typer.Option(help="Retrieval model file to write (a .json beside it).")] = Path(
        "runs/retrieval.pt"
    ),
    steps: Annotated[int, typer.Option(help="Training steps.")] = 400,
    area: Annotated[str, typer.Option(help="Training ground: fractions of the width, a,b.")] = "0,0.5",
    threads: Annotated[int | None, typer.Option(help="torch CPU threads.")] = None,
) -> None:
    """Train the cnn global index's descriptor: the same ground in two years is a positive."""
    import torch

    from orthonav.models import shipped_model_path
    from orthonav.models.retrieval import RetrievalTrainConfig, train_retrieval_model
    from orthonav.models.train import dates_in

    if threads:
        torch.set_num_threads(threads)
    fractions = _csv(area, "--area", float)
    config = RetrievalTrainConfig(steps=steps, area=(fractions[0], fractions[-1]))
    command = f"orthonav map train-index --data {data} --dates {dates} --steps {steps} --area {area}"
    years = dates_in(data, list(_csv(dates, "--dates")))
    info = train_retrieval_model(years, out, config, shipped_model_path(), command)
    console.print(f"written {out} ({info['train_seconds']} s, loss {info['loss_first_last_20']})")


@map_app.command("corridor")
def map_corridor(
    map_dir: Annotated[Path, typer.Argument(help="Map package directory to cut from.")],
    route: Annotated[Path, typer.Option(help="The mission's route: a GeoJSON LineString (WGS84).")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Corridor package directory to write.")],
    width: Annotated[str, typer.Option(help="Corridor width across the route: 2km, 500m or metres.")] = "2km",
    overwrite: Annotated[bool, typer.Option(help="Replace an existing package.")] = False,
) -> None:
    """Cut a mission's corridor into a small, self-contained map package for the drone."""
    from orthonav.mapdb import MapPackage, cut_corridor, read_route

    package = MapPackage(map_dir)
    corridor = cut_corridor(package, read_route(route), parse_length_m(width, "--width"), out, overwrite)
    _print_dict(f"corridor package {out} ({len(corridor)} of {len(package)} tiles)", corridor.summary())


@app.command()
def localize(
    map_dir: Annotated[Path, typer.Argument(help="Map package directory.")],
    frames: Annotated[Path, typer.Argument(help="A frame image, or a folder of frames.")],
    prior_lat: Annotated[float | None, typer.Option(help="Prior latitude (deg).")] = None,
    prior_lon: Annotated[float | None, typer.Option(help="Prior longitude (deg).")] = None,
    heading: Annotated[float | None, typer.Option(help="Prior heading (deg from north).")] = None,
    altitude: Annotated[float | None, typer.Option(help="Altitude above ground (m).")] = None,
    pitch: Annotated[float | None, typer.Option(help="Pitch from the autopilot (deg).")] = None,
    roll: Annotated[float | None, typer.Option(help="Roll from the autopilot (deg).")] = None,
    sigma: Annotated[float, typer.Option(help="Prior position 1-sigma (m).")] = 200.0,
    priors: Annotated[Path | None, typer.Option(help="Priors CSV for a folder of frames.")] = None,
    camera_json: Annotated[
        Path | None, typer.Option("--camera", help="Camera JSON (default: the map's).")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per frame on stdout.")] = False,
    out: Annotated[Path | None, typer.Option(help="Write fixes as JSON lines.")] = None,
    plot: Annotated[Path | None, typer.Option(help="PNG of the fixes' footprints over the map.")] = None,
    features: Annotated[
        str | None, typer.Option(help="Expected feature backend (default: the one that built the map).")
    ] = None,
    weights: Annotated[str | None, typer.Option(help=_WEIGHTS_HELP + " Default: the map's.")] = None,
    device: Annotated[str, typer.Option(help=_DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP)] = None,
) -> None:
    """Localize frames against a map; rejected fixes say why."""
    from orthonav.frames import load_frame
    from orthonav.localize import Localizer, check_backend
    from orthonav.mapdb import MapPackage
    from orthonav.types import Fix, Prior

    package = MapPackage(map_dir)
    if features:
        check_backend(package, features)
    camera = Camera.from_json(camera_json) if camera_json else package.camera
    backend = package.create_backend(Runtime(device, threads), **weights_conf(package.backend_name, weights))
    localizer = Localizer(package, camera, backend=backend)
    single = Prior(prior_lat, prior_lon, altitude, heading, pitch, roll, sigma_m=sigma)
    batch = frames.is_dir()
    paths = list_images(frames) if batch else [frames]
    table_priors = read_priors(priors) if priors else {}
    records, fixes = [], []
    sink = open(out, "w") if out else None  # noqa: SIM115  (one line per frame, flushed as it goes)
    try:
        for path in paths:
            try:
                fix = localizer.localize(load_frame(path), table_priors.get(path.name, single))
            except OrthonavError as exc:
                if not batch:
                    raise
                fix = Fix(False, str(exc))  # one bad frame is a rejection, not the end of the batch
            fixes.append((path.name, fix))
            record = {"name": path.name, **fix.to_dict()}
            records.append(record)
            if as_json:
                print(json.dumps(record), flush=True)
            if sink:
                sink.write(json.dumps(record) + "\n")
                sink.flush()
    finally:
        if sink:
            sink.close()
    if not as_json:
        _print_fixes(records)
    if plot:
        from orthonav.viz import plot_fixes

        plot_fixes(package, fixes, camera, plot)


def _print_fixes(records: list[dict]) -> None:
    table = Table(title="fixes")
    for col in ("frame", "accepted", "lat", "lon", "alt m", "heading", "sigma m", "inliers", "ms", "reason"):
        table.add_column(col)
    for r in records:

        def f(key: str, fmt: str, rec: dict = r) -> str:
            return "" if rec.get(key) is None else format(rec[key], fmt)

        table.add_row(
            r["name"],
            "yes" if r["accepted"] else "[red]no[/]",
            f("lat", ".6f"),
            f("lon", ".6f"),
            f("altitude", ".0f"),
            f("heading", ".1f"),
            f("sigma_m", ".1f"),
            str(r.get("inliers", "")),
            f"{r.get('timings', {}).get('total_ms', 0):.0f}",
            r["reason"],
        )
    table_console.print(table)


@app.command()
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
) -> None:
    """Fly the mission loop (INS + visual fixes + filter) over a map; write logs, plot and summary."""
    from orthonav.geo import GeoRaster
    from orthonav.mapdb import MapPackage
    from orthonav.sim import MissionConfig, run_mission

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
    with GeoRaster(source) as frames:
        result = run_mission(package, frames, package.camera, config, out)
    _print_dict("mission", result.summary())


@app.command()
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
    _print_dict("demo mission", result.summary())
    console.print(
        f"outputs: {out / 'run'} (trajectory.png, steps.jsonl, summary.json); map: {out / 'map'}",
        soft_wrap=True,
    )


_DEFAULT_DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"
_BENCH_COLUMNS = {
    "features": "features",
    "condition": "condition",
    "prior": "prior",
    "map": "map",
    "frames_from": "frames",
    "n": "n",
    "fix_rate": "fix",
    "within_10m": "<=10m",
    "within_25m": "<=25m",
    "centre_within_2px": "ctr<=2px",
    "median_m": "med m",
    "p95_m": "p95 m",
    "false_fix_rate": "false",
    "within_3sigma": "<=3sig",
    "keypoints": "kp",
    "matches": "matches",
    "inliers": "inl",
    "total_ms": "ms",
}


@bench_app.command("localize")
def bench_localize(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        _DEFAULT_DATA / "naip"
    ),
    highres: Annotated[Path | None, typer.Option(help="Folder of drone-scale orthophotos.")] = (
        _DEFAULT_DATA / "highres"
    ),
    frames: Annotated[int, typer.Option(help="Frames per condition.")] = 20,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    features: Annotated[
        str,
        typer.Option(
            help="Feature backends, comma-separated, run side by side; 'all' = every installed one."
        ),
    ] = "orb",
    weights: Annotated[
        str | None, typer.Option(help="superpoint's SUPERPOINT.pth,SUPERGLUE.pth (it is skipped without).")
    ] = None,
    speed_sizes: Annotated[
        str, typer.Option(help="Frame widths for the speed table, comma-separated ('' skips it).")
    ] = "320,640,1024",
    device: Annotated[str, typer.Option(help=_DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP)] = None,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG is written beside it).")] = Path(
        "runs/bench_localize.json"
    ),
) -> None:
    """Cross-date and same-date localization benchmark on real orthophotos."""
    from orthonav.bench import LocalizeBenchConfig, run_localize_benchmark
    from orthonav.features import available_backends

    if not data.is_dir():
        raise OrthonavError(f"{data}: no such data folder (pass --data DIR of GeoTIFFs)")
    names = [n for n in available_backends() if n != "superpoint" or weights] if features == "all" else []
    names = names or [n.strip() for n in features.split(",") if n.strip()]
    backend_conf = {"superpoint": weights_conf("superpoint", weights)} if weights else {}
    try:
        sizes = tuple(int(v) for v in speed_sizes.split(",") if v.strip())
    except ValueError:
        raise OrthonavError(
            f"--speed-sizes: expected comma-separated pixel widths, got {speed_sizes!r}"
        ) from None
    config = LocalizeBenchConfig(frames=frames, seed=seed, features=tuple(names), speed_sizes=sizes)
    result = run_localize_benchmark(
        data,
        highres if highres and highres.is_dir() else None,
        out,
        config,
        runtime=Runtime(device, threads),
        backend_conf=backend_conf,
    )
    table = Table(title=f"bench localize ({config.width}x{config.height} frames)", box=None)
    for title in _BENCH_COLUMNS.values():
        table.add_column(title, justify="right")
    for row in result["rows"]:
        table.add_row(*(_cell(row.get(key)) for key in _BENCH_COLUMNS))
    table_console.print(table)
    summary = dict(result["summary"])
    targets = summary.pop("targets")
    pooled = Table(title="pooled by backend and condition", box=None)
    columns = ("n", "fix_rate", "within_10m", "within_25m", "centre_within_2px", "false_fix_rate")
    for title in ("backend: condition / prior", *columns, "median ms"):
        pooled.add_column(title, justify="right")
    for key, value in summary.items():
        pooled.add_row(key, *(_cell(value[c]) for c in columns), _cell(value["median_total_ms"]))
    table_console.print(pooled)
    _print_rows(
        f"speed over frame sizes (median ms, frame vs 4 tiles; {result['speed']['image']})",
        result["speed"]["rows"],
    )
    for name, ok in targets.items():
        console.print(f"target {name}: {'[green]met[/]' if ok else '[red]not met[/]'}")
    console.print(f"peak RSS {result['peak_rss_mb']} MB; written {out} and {out.with_suffix('.png')}")


def _print_rows(title: str, rows: list[dict]) -> None:
    if not rows:
        return
    table = Table(title=title, box=None)
    for key in rows[0]:
        table.add_column(key, justify="right")
    for row in rows:
        table.add_row(*(_cell(v) for v in row.values()))
    table_console.print(table)


def _cell(value: object) -> str:
    if value is None:
        return "-"
    if isinstance(value, str):
        return value[-8:] if value[-8:].isdigit() else value  # dated file names: the date
    return f"{value:g}"


def _csv(text: str, option: str, kind: type = str) -> tuple:
    try:
        values = tuple(kind(v.strip()) for v in text.split(",") if v.strip())
    except ValueError:
        raise OrthonavError(f"{option} {text!r}: expected comma-separated {kind.__name__} values") from None
    if not values:
        raise OrthonavError(f"{option}: expected at least one value")
    return values


@bench_app.command("correction")
def bench_correction(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        _DEFAULT_DATA / "naip"
    ),
    neon: Annotated[Path | None, typer.Option(help="Folder of two season folders of plots ('' skips).")] = (
        _DEFAULT_DATA / "neon_sjer"
    ),
    frames: Annotated[int, typer.Option(help="Frames per ordered pair of dates.")] = 8,
    dates: Annotated[str, typer.Option(help="Evaluation dates (never the model's training dates).")] = (
        "20090818,20150926,20200831"
    ),
    backbones: Annotated[str, typer.Option(help="Backbones, comma-separated.")] = (
        "gradient,trained,vgg11,resnet18,mobilenetv2"
    ),
    sizes: Annotated[str, typer.Option(help="Frame sizes for matching (px).")] = "224,448",
    errors: Annotated[str, typer.Option(help="Initial INS errors (m).")] = "10,15,50,100,200",
    keypoints: Annotated[
        str, typer.Option(help="Keypoint backends for comparison ('' skips).")
    ] = "orb,aliked",
    model: Annotated[Path | None, typer.Option(help="Model file for 'trained' (default: shipped).")] = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP)] = None,
    out: Annotated[Path, typer.Option(help="JSON output (PNGs are written beside it).")] = Path(
        "runs/bench_correction.json"
    ),
) -> None:
    """Seed B's INS-correction experiment on real cross-date imagery, every backbone side by side."""
    from orthonav.bench.correction import CorrectionBenchConfig, run_correction_benchmark

    if not data.is_dir():
        raise OrthonavError(f"{data}: no such data folder (pass --data DIR of GeoTIFFs)")
    if threads:
        import torch

        torch.set_num_threads(threads)
    config = CorrectionBenchConfig(
        frames=frames,
        seed=seed,
        eval_dates=_csv(dates, "--dates"),
        backbones=_csv(backbones, "--backbones"),
        sizes=_csv(sizes, "--sizes", int),
        initial_errors_m=_csv(errors, "--errors", float),
        keypoint_features=tuple(k.strip() for k in keypoints.split(",") if k.strip()),
        model_path=str(model) if model else None,
    )
    result = run_correction_benchmark(data, neon if neon and neon.is_dir() else None, out, config)
    _print_rows("correction vs keypoints, NAIP cross-date (errors in m, rates of all frames)", result["rows"])
    _print_rows("time per correction (median ms)", result["speed"])
    route = result["route"]
    _print_rows(
        f"route {route['frames']} frames over {route['map']} map",
        [{"track": k, **v} for k, v in route["stats"].items()],
    )
    if result["neon"]:
        _print_rows(f"NEON cross-season, {result['neon']['plots']} plots (m)", result["neon"]["rows"])
    for name, ok in result["targets"].items():
        console.print(f"target {name}: {'[green]met[/]' if ok else '[red]not met[/]'}")
    console.print(f"written {out}, {out.with_suffix('.png')} and {out.with_name(out.stem + '_route.png')}")


@bench_app.command("mission")
def bench_mission(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        _DEFAULT_DATA / "naip"
    ),
    map_date: Annotated[str, typer.Option(help="The map's GeoTIFF: a unique part of its name.")] = "2018",
    frames_date: Annotated[str, typer.Option(help="The frames' GeoTIFF (another date).")] = "2020",
    missions: Annotated[int, typer.Option(help="Missions per backend.")] = 30,
    features: Annotated[str, typer.Option(help="Feature backends, comma-separated, side by side.")] = "orb",
    imu: Annotated[str, typer.Option(help="IMU error model: perfect, tactical, consumer.")] = "consumer",
    altitude: Annotated[float, typer.Option(help="Altitude AGL (m).")] = 1000.0,
    min_leg: Annotated[float, typer.Option(help="Least start-to-target distance (m).")] = 1500.0,
    latency_s: Annotated[
        float, typer.Option(help="Seconds of companion mode (sim vehicle over UDP) for the latency; 0 skips.")
    ] = 30.0,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    device: Annotated[str, typer.Option(help=_DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=_THREADS_HELP)] = None,
    out: Annotated[Path, typer.Option(help="JSON output (a PNG and the runs are written beside it).")] = Path(
        "runs/bench_mission.json"
    ),
) -> None:
    """The thesis's experiment: N missions per backend, GNSS lost, INS drifting, fixes fused."""
    from orthonav.bench.mission import MissionBenchConfig, run_mission_benchmark

    config = MissionBenchConfig(
        missions=missions,
        features=_csv(features, "--features"),
        seed=seed,
        imu=imu,
        alt_m=altitude,
        min_leg_m=min_leg,
        latency_s=latency_s,
    )
    map_tif, frames_tif = _dated(data, map_date, "--map-date"), _dated(data, frames_date, "--frames-date")
    result = run_mission_benchmark(map_tif, frames_tif, out, config, runtime=Runtime(device, threads))
    _print_rows(
        f"{missions} missions per backend, map {map_tif.stem}, frames {frames_tif.stem}, {imu} IMU",
        [{"features": k, **v} for k, v in result["summary"].items()],
    )
    _print_rows("companion mode over UDP: frame capture -> MAVLink message (ms)", result["latency"])
    console.print(f"written {out} and {out.with_suffix('.png')}; runs in {out.with_suffix('')}")


@bench_app.command("relocalize")
def bench_relocalize(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        _DEFAULT_DATA / "naip"
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
            "(dense gradient correlation around the index's top tiles)."
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
        blocks=_csv(blocks, "--blocks", int),
        frames=frames,
        alt_m=altitude,
        features=features,
        words=words,
        indexes=_csv(index, "--index", str),
        seed=seed,
        all_tiles=all_tiles,
        fix_sources=_csv(fix_sources, "--fix-sources", str),
    )
    result = run_relocalize_benchmark(sources, out, config)
    title = f"lost frames ({features}, {altitude:g} m): index top {config.candidates} vs every tile"
    _print_rows(title, result["rows"])
    console.print(f"written {out} and {out.with_suffix('.png')}")


@bench_app.command("mapbuild")
def bench_mapbuild(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        _DEFAULT_DATA / "naip"
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
        blocks=_csv(blocks, "--blocks", int), workers=_csv(workers, "--workers", int), alt_m=altitude
    )
    result = run_mapbuild_benchmark(_sources(data), out, config)
    _print_rows("map build (ORB): throughput and peak memory", result["rows"])
    console.print(f"written {out} and {out.with_suffix('.png')}")


@bench_app.command("slam")
def bench_slam(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        _DEFAULT_DATA / "naip"
    ),
    map_date: Annotated[str, typer.Option(help="The map GeoTIFF of the fixes: part of its name.")] = "2018",
    frames_date: Annotated[str, typer.Option(help="The frames' GeoTIFF (another date).")] = "2020",
    seeds: Annotated[int, typer.Option(help="Worlds (flights) per setup; medians are over them.")] = 3,
    keyframes: Annotated[int, typer.Option(help="Keyframes per flight (8 s apart at 20 m/s).")] = 24,
    fix_source: Annotated[str, typer.Option(help="Map fixes: correlation (dense) or orb (keypoints).")] = (
        "correlation"
    ),
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
    _print_rows(
        f"SLAM over {frames_tif.stem}, fixes: {fix_source} on {map_tif.stem} (medians of {seeds})",
        result["summary"],
    )
    stereo = result["stereo"]["median"]
    if stereo:
        _print_rows(
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


if __name__ == "__main__":
    main()
