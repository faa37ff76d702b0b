"""``orthonav map``: build, inspect, index and cut map packages, and attach terrain heights."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer

from orthonav.cli.inputs import (
    DEVICE_HELP,
    THREADS_HELP,
    WEIGHTS_HELP,
    camera_from_options,
    parse_length_m,
    weights_conf,
)
from orthonav.cli.output import console, csv_values, print_dict
from orthonav.errors import OrthonavError
from orthonav.features import Runtime

map_app = typer.Typer(help="Build and inspect map packages.", no_args_is_help=True)

DSM_HELP = (
    "DSM/DEM GeoTIFF of heights in metres (any CRS and resolution): the terrain the pose is solved on "
    "(default: flat ground)."
)


@map_app.command("build")
def map_build(
    ortho: Annotated[
        Path,
        typer.Argument(help="GeoTIFF/COG orthophoto (any CRS), a VRT, or a folder of GeoTIFFs to mosaic."),
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Map package directory to write.")],
    camera_json: Annotated[Path | None, typer.Option("--camera", help="Camera JSON.")] = None,
    dsm: Annotated[Path | None, typer.Option("--dsm", help=DSM_HELP)] = None,
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
    max_frame_px: Annotated[
        int | None,
        typer.Option(
            help="Frames are matched at most this many pixels across: a map finer than that is "
            "tiled coarser (cost follows pixels, not the orthophoto's resolution); 0: no limit. "
            "Default: the backend's, 512 for aliked, aliked-n16rot and disk, 800 for the others."
        ),
    ] = None,
    features: Annotated[
        str,
        typer.Option(
            help="Feature backend: orb, sift, aliked, disk, xfeat, superpoint (docs: How it works)."
        ),
    ] = "orb",
    max_keypoints: Annotated[int, typer.Option(help="Keypoints per tile.")] = 1024,
    weights: Annotated[str | None, typer.Option(help=WEIGHTS_HELP)] = None,
    device: Annotated[str, typer.Option(help=DEVICE_HELP)] = "cpu",
    threads: Annotated[int | None, typer.Option(help=THREADS_HELP)] = None,
    overwrite: Annotated[bool, typer.Option(help="Replace an existing package.")] = False,
    yes: Annotated[
        bool, typer.Option("--yes", help="Build a very large map (hours, gigabytes) without asking.")
    ] = False,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Build on a local Dask cluster of N worker processes (needs the extra orthonav\\[scale])."
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Build on an existing Dask cluster at this scheduler address (tcp://HOST:PORT); "
            "its workers must see the orthophoto and the output folder at the same paths."
        ),
    ] = None,
) -> None:
    """Tile an orthophoto and extract features into a map package (resumable, atomic): an
    interrupted build (Ctrl-C, SIGTERM) keeps every tile built, and a rerun resumes there."""
    from orthonav.geo.mosaic import build_vrt, mosaic_sources
    from orthonav.mapdb import TilingConfig, build_map
    from orthonav.mapdb.build import LARGE_MAP_TILES, BuildReport

    start = time.perf_counter()
    report = BuildReport(say=lambda line: console.print(line, soft_wrap=True))
    if ortho.is_dir():
        # The mosaic (and any reprojected copies) lives beside the package, which refers to it.
        mosaic = out.with_name(out.name + ".mosaic") / "mosaic.vrt"
        ortho = build_vrt(mosaic_sources(ortho), mosaic, crs)
    elif crs:
        raise OrthonavError(f"--crs {crs}: applies to a folder of GeoTIFFs; {ortho} is one file")
    package = build_map(
        ortho,
        out,
        camera_from_options(camera_json, width, height, hfov),
        TilingConfig(altitude, scale_coef, overlap, max_frame_px),
        features,
        {"max_keypoints": max_keypoints, **weights_conf(features, weights)},
        overwrite=overwrite,
        runtime=Runtime(device, threads),
        workers=workers,
        scheduler=scheduler,
        dsm=dsm,
        max_tiles=None if yes else LARGE_MAP_TILES,
        report=report,
    )
    elapsed_s = time.perf_counter() - start
    print_dict(f"map package {out}", package.summary())
    built = f"{report.built} built in {elapsed_s:.1f} s ({report.built / elapsed_s:.1f} tiles/s)"
    reused = f", {report.reused} reused from the interrupted build" if report.reused else ""
    console.print(f"{len(package)} tiles: {built}{reused}", soft_wrap=True)


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
        print_dict(f"map package {map_dir}", summary)


@map_app.command("verify")
def map_verify(map_dir: Annotated[Path, typer.Argument(help="Map package directory.")]) -> None:
    """Check every file of a map package against its checksum: exit 0 intact, 2 damaged (the
    files, and the tiles and area they hold, in one line). `fly` runs the same check at start."""
    from orthonav.mapdb import MapPackage

    package = MapPackage(map_dir)
    package.require_intact()
    chunks = -(-len(package) // package.chunk_tiles)
    console.print(
        f"map {map_dir}: intact ({len(package)} tiles, {chunks} feature chunks, every checksum matches)",
        soft_wrap=True,
    )


@map_app.command("terrain")
def map_terrain(
    map_dir: Annotated[Path, typer.Argument(help="Map package directory.")],
    dsm: Annotated[Path, typer.Argument(help=DSM_HELP)],
) -> None:
    """Attach terrain heights from a DSM/DEM to a map package (replaces any attached before)."""
    from orthonav.mapdb import MapPackage, attach_terrain

    package = attach_terrain(MapPackage(map_dir), dsm, progress=True)
    console.print(f"terrain -> {package.path / 'terrain.tif'}: {package.terrain.describe()}", soft_wrap=True)


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
    fractions = csv_values(area, "--area", float)
    config = RetrievalTrainConfig(steps=steps, area=(fractions[0], fractions[-1]))
    command = f"orthonav map train-index --data {data} --dates {dates} --steps {steps} --area {area}"
    years = dates_in(data, list(csv_values(dates, "--dates")))
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
    print_dict(f"corridor package {out} ({len(corridor)} of {len(package)} tiles)", corridor.summary())
