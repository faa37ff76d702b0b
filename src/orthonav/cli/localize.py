"""``orthonav localize``: frames against a map package, one fix or rejection each."""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table
from tqdm import tqdm

from orthonav.atomic import is_special, open_output
from orthonav.camera import Camera
from orthonav.cli.inputs import (
    DEVICE_HELP,
    FALLBACK_HELP,
    FIX_SOURCE_HELP,
    THREADS_HELP,
    TRUNK_CHECK_HELP,
    WEIGHTS_HELP,
    fix_source_option,
    parse_latlon,
    read_priors,
    trunk_check_option,
    weights_conf,
)
from orthonav.cli.output import console, say_fix_source, table_console
from orthonav.errors import OrthonavError
from orthonav.features import Runtime
from orthonav.frames import list_images
from orthonav.localize import CORRELATION, open_fix_sources
from orthonav.mapdb import MapPackage
from orthonav.types import Prior


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
            help="PNG of the fixes' footprints over the map, and an interactive HTML map beside it "
            "(none beside a device such as /dev/null)."
        ),
    ] = None,
    features: Annotated[
        str | None, typer.Option(help="Expected feature backend (default: the one that built the map).")
    ] = None,
    weights: Annotated[str | None, typer.Option(help=WEIGHTS_HELP + " Default: the map's.")] = None,
    device: Annotated[str, typer.Option(help=DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=THREADS_HELP)] = None,
    fix_source: Annotated[str | None, typer.Option(help=FIX_SOURCE_HELP)] = None,
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
        name = fix_source_option(fix_source)
        backend = None
        if name != CORRELATION:  # the map's keypoints, alone or the cascade's, on --device
            backend = package.create_backend(runtime, **weights_conf(package.backend_name, weights))
        opened = open_fix_sources(
            stack, package, camera, name, fallback or [], backend=backend, runtime=runtime, trunk_check=checks
        )
        say_fix_source(opened)
        source = opened.source
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
        from orthonav.viz.fixes import plot_fixes
        from orthonav.viz.html import write_fixes_html

        frame_priors = {p.name: table_priors.get(p.name, single) for p in paths}
        plot_fixes(package, fixes, camera, plot, priors=frame_priors)
        if not is_special(plot):
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


def _print_fixes(records: list[dict]) -> None:
    """One row a frame; ``source`` is the fix source that answered (in a chain, which one)."""
    table = Table(title="fixes")
    columns = ("frame", "accepted", "source", "lat", "lon", "alt m", "heading", "sigma m", "inliers", "ms")
    for col in (*columns, "reason"):
        table.add_column(col)
    for r in records:

        def f(key: str, fmt: str, rec: dict = r) -> str:
            return "" if rec.get(key) is None else format(rec[key], fmt)

        table.add_row(
            r["name"],
            "yes" if r["accepted"] else "[red]no[/]",
            r.get("method") or "",
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
