"""``orthonav localize``: frames against a map package, one fix or rejection each."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table
from tqdm import tqdm

from orthonav.atomic import open_output
from orthonav.camera import Camera
from orthonav.cli.inputs import (
    DEVICE_HELP,
    THREADS_HELP,
    TRUNK_CHECK_HELP,
    WEIGHTS_HELP,
    parse_latlon,
    read_priors,
    weights_conf,
)
from orthonav.cli.output import console, err_console, table_console
from orthonav.errors import OrthonavError
from orthonav.features import Runtime
from orthonav.frames import list_images
from orthonav.geo import GeoRaster
from orthonav.localize import Fallback, LocalizerConfig, learned_parts, map_orthophoto, warm_up
from orthonav.localize.cascade import (
    CORRELATION,
    DEFAULT_COARSE_BACKBONE,
    FIX_SOURCES,
    ChosenFixSource,
    open_fix_source,
    trunk_check_option,
)
from orthonav.mapdb import MapPackage
from orthonav.types import FixSource, Prior

FALLBACK_HELP = (
    "Another map package of the same area, built with another backend, asked where this map's fix "
    "is rejected (e.g. an ALIKED map behind an ORB one: ORB's time on most frames, ALIKED's fixes "
    "on the rest). Repeat for more, in order."
)
FIX_SOURCE_HELP = (
    f"{' | '.join(FIX_SOURCES)}: the cascade (dense correlation with the map's orthophoto, keypoints "
    "near it, verification, a calibrated acceptance: robust across dates), the map's keypoints "
    "alone, or dense gradient correlation alone. Default: the cascade where the map's orthophoto "
    "(recorded in its manifest) is there, else keypoints, saying why."
)


def localize(
    map_dir: Annotated[Path, typer.Argument(help="Map package directory.")],
    frames: Annotated[Path, typer.Argument(help="A frame image, or a folder of frames.")],
    prior: Annotated[
        str | None, typer.Option(help="Prior position LAT,LON (deg), e.g. from the INS.")
    ] = None,
    heading: Annotated[float | None, typer.Option(help="Prior heading (deg from north).")] = None,
    altitude: Annotated[float | None, typer.Option(help="Altitude above ground (m).")] = None,
    pitch: Annotated[float | None, typer.Option(help="Pitch from the autopilot (deg).")] = None,
    roll: Annotated[float | None, typer.Option(help="Roll from the autopilot (deg).")] = None,
    prior_sigma: Annotated[float, typer.Option(help="Prior position 1-sigma (m).")] = 200.0,
    priors: Annotated[Path | None, typer.Option(help="Priors CSV for a folder of frames.")] = None,
    camera_json: Annotated[
        Path | None, typer.Option("--camera", help="Camera JSON (default: the map's).")
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="One JSON object per frame on stdout.")] = False,
    out: Annotated[Path | None, typer.Option(help="Write fixes as JSON lines.")] = None,
    plot: Annotated[
        Path | None,
        typer.Option(
            help="PNG of the fixes' footprints over the map, and an interactive HTML map beside it."
        ),
    ] = None,
    features: Annotated[
        str | None, typer.Option(help="Expected feature backend (default: the one that built the map).")
    ] = None,
    weights: Annotated[str | None, typer.Option(help=WEIGHTS_HELP + " Default: the map's.")] = None,
    device: Annotated[str, typer.Option(help=DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=THREADS_HELP)] = None,
    fix_source: Annotated[
        str,
        typer.Option(
            help="keypoints (the map's features), correlation (dense gradient correlation with "
            "the map's orthophoto around the prior: robust across dates, needs position, "
            "altitude and heading priors) or cascade (correlation, then keypoints near it, "
            "verification and a calibrated acceptance: robust across dates, no false fixes; "
            "without a heading prior it tries 12 headings)."
        ),
    ] = "keypoints",
    fallback: Annotated[list[Path] | None, typer.Option(help=FALLBACK_HELP)] = None,
    trunk_check: Annotated[str, typer.Option(help=TRUNK_CHECK_HELP)] = "auto",
) -> None:
    """Localize frames against a map; rejected fixes say why."""
    from orthonav.frames import load_frame
    from orthonav.localize import BatchSummary, check_backend, localize_files
    from orthonav.mapdb import MapPackage

    start = time.perf_counter()
    package = MapPackage(map_dir)
    if features:
        check_backend(package, features)
    camera = Camera.from_json(camera_json) if camera_json else package.camera
    lat, lon = parse_latlon(prior, "--prior") if prior else (None, None)
    single = Prior(lat, lon, altitude, heading, pitch, roll, sigma_m=prior_sigma)
    paths = list_images(frames) if frames.is_dir() else [frames]
    table_priors = read_priors(priors, paths) if priors else {}
    records, fixes, summary = [], [], BatchSummary()
    with ExitStack() as stack:
        runtime = Runtime(device, threads)
        checks = trunk_check_option(trunk_check)
        source = _fix_source(stack, fix_source, package, camera, runtime, weights, checks)
        source = chain_fallbacks(
            source,
            package,
            fallback or [],
            fix_source,
            lambda more: _fix_source(stack, fix_source, more, camera, runtime, None, checks),
        )
        if frames.is_dir():
            results = localize_files(source, paths, table_priors, single)
        else:  # one frame: a bad file or frame is an error, not a rejection
            results = iter(
                [(frames, source.localize(load_frame(frames), table_priors.get(frames.name, single)))]
            )
        sink = stack.enter_context(open_output(out)) if out else None  # one line per frame, as it goes
        if not as_json and len(paths) > 1:
            results = stack.enter_context(tqdm(results, total=len(paths), unit="frame", desc="localize"))
        for path, fix in results:
            summary.add(fix)
            fixes.append((path.name, fix))
            record = {"name": path.name, **fix.to_dict()}
            records.append(record)
            if as_json:
                print(json.dumps(record), flush=True)
            if sink:
                sink.write(json.dumps(record) + "\n")
                sink.flush()
    if not as_json:
        _print_fixes(records)
    if plot:
        from orthonav.viz import plot_fixes
        from orthonav.viz.html import write_fixes_html

        frame_priors = {p.name: table_priors.get(p.name, single) for p in paths}
        plot_fixes(package, fixes, camera, plot, priors=frame_priors)
        write_fixes_html(
            package, fixes, camera, plot.with_suffix(".html"), frame_priors, f"fixes on {map_dir.name}"
        )
    if not as_json:
        console.print(f"localize: {summary.line(time.perf_counter() - start)}")
    require_a_prior_on_the_map(package, [table_priors.get(p.name, single) for p in paths])


def require_a_prior_on_the_map(package: MapPackage, priors: Sequence[Prior]) -> None:
    """Frames whose every prior position is off the map are a mistake in the priors or the map,
    not a batch of rejections: one line saying where they are and where the map is (as replay
    says of a flight off the map), and exit code 2."""
    placed = [p for p in priors if p.has_position]
    if not placed or any(package.within_reach(p.lat, p.lon, p.sigma_m) for p in placed):
        return
    raise OrthonavError(
        f"none of the {len(placed)} frames' prior positions is on the map {package.path} (within 3 x "
        f"their sigma): they are {package.away([p.lat for p in placed], [p.lon for p in placed])}; "
        "check the priors (--priors, --prior) and the map"
    )


def _fix_source(
    stack: ExitStack,
    name: str,
    package: MapPackage,
    camera: Camera,
    runtime: Runtime,
    weights: str | None,
    trunk_check: bool | None,
) -> FixSource:
    """The fix source ``name``, keypoint matching with the map's backend where it matches."""
    backend = None
    if name != CORRELATION:
        backend = package.create_backend(runtime, **weights_conf(package.backend_name, weights))
    return open_fix_source(stack, package, camera, name, backend=backend, trunk_check=trunk_check).source


def chain_fallbacks(
    first: FixSource,
    package: MapPackage,
    fallbacks: Sequence[Path],
    name: str,
    open_source: Callable[[MapPackage], FixSource],
) -> FixSource:
    """``first`` (the fix source ``name`` on ``package``), or where ``fallbacks`` name more map
    packages, a :class:`Fallback` asking each one's fix source (``open_source``) in turn."""
    if not fallbacks:
        return first
    if name == CORRELATION:
        raise OrthonavError(
            "--fallback: correlation matches the orthophoto, not a map's features; "
            "use it with --fix-source keypoints or cascade"
        )
    packages = [MapPackage(path) for path in fallbacks]
    names = [each.backend_name for each in (package, *packages)]
    return Fallback([first, *(open_source(more) for more in packages)], names)


def flight_fix_source(
    stack: ExitStack,
    package: MapPackage,
    camera: Camera,
    name: str | None,
    orthophoto: Path | None = None,
    localizer: LocalizerConfig | None = None,
    fallbacks: Sequence[Path] = (),
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE,
    trunk_check: bool | None = None,
) -> FixSource:
    """The fix source of a flight (``fly``, ``simulate``) by ``--fix-source``, with the maps of
    ``fallbacks`` behind it, each warmed up (each cascade's trunk check ``trunk_check``); on
    stderr, once: which one runs, how it treats frames without a position prior, where the
    default cascade cannot run, why keypoints run instead, and how each map's warm-up went.
    Maps of one orthophoto (``--map orb --fallback aliked``) share it opened once, with its
    in-memory views."""

    def open_source(map_package: MapPackage, source_name: str | None) -> ChosenFixSource:
        chosen = open_fix_source(
            stack,
            map_package,
            camera,
            source_name,
            orthophoto,
            localizer,
            coarse_backbone=coarse_backbone,
            rasters=rasters,
            trunk_check=trunk_check,
        )
        opened.append((chosen, map_package))
        return chosen

    opened: list[tuple[ChosenFixSource, MapPackage]] = []
    rasters: dict[Path, GeoRaster] = {}
    chosen = open_source(package, name)
    if chosen.fallback:
        err_console.print(f"[yellow]{escape(chosen.fallback)}[/]", soft_wrap=True)
    source = chain_fallbacks(
        chosen.source, package, fallbacks, chosen.name, lambda more: open_source(more, chosen.name).source
    )
    chain = ""
    if isinstance(source, Fallback):
        chain = f" ({', then '.join(source.names)} where the one before rejects)"
    note = f"; {chosen.note}" if chosen.note else ""
    err_console.print(escape(f"fix source: {chosen.name}{chain}{note}"), highlight=False, soft_wrap=True)
    for each, map_package in opened:
        for line in _warmed(each, camera, map_package, rasters):
            err_console.print(escape(line), highlight=False, soft_wrap=True)
    return source


def _warmed(
    chosen: ChosenFixSource, camera: Camera, package: MapPackage, rasters: dict[Path, GeoRaster]
) -> list[str]:
    """Warm one map's fix source up on the map's own picture (:func:`warm_up`), rendered from
    the orthophoto it reads, or for keypoints alone from the map's orthophoto where it is there
    (one the flight holds open already, else opened for this only); say how it went, and where
    its learned parts run (:func:`learned_parts`). A fallback map is warmed too: it is asked
    when the first map fails, and should not then pay for its first frame; so is the network of
    its global index, which the first lost frame would load (and, the first time on a machine,
    export for ONNX Runtime). A warm-up that cannot run does not stop the flight."""
    start = time.perf_counter()
    try:
        with ExitStack() as stack:
            raster = chosen.raster
            if raster is None:  # keypoints alone: the orthophoto if the flight holds it open
                path = map_orthophoto(package).resolve()
                raster = rasters[path] if path in rasters else stack.enter_context(GeoRaster(path))
            fix = warm_up(chosen.source, raster, camera, package.tiling.nominal_alt_m)
            if package.global_index is not None:
                package.global_index.prepare()
            parts = learned_parts(chosen.source)
    except OrthonavError as exc:
        return [f"{package.path.name}: not warmed up, its first frame will be slower ({exc})"]
    outcome = "fixed" if fix.accepted else f"not fixed: {fix.reason}"
    warmed = (
        f"{package.path.name}: warmed up in {time.perf_counter() - start:.1f} s on the map's own picture "
        f"at its centre ({outcome})"
    )
    return [warmed, *parts]


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
