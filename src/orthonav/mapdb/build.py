"""Build a map package from an orthophoto: tile, extract features, write atomically.

The build works in ``MAP_DIR.partial/``. Each tile's features are saved as soon as they are
done (``progress/tile_*.npy``), and gathered into the package's chunk files of
``CHUNK_TILES`` tiles when a chunk is complete; every saved part is sealed with its checksum
(``progress/*.sha256``). A build that is interrupted (Ctrl-C, SIGTERM, a crash) and started
again with the same source and settings reuses every sealed part, whatever the map's size,
and builds again any part whose checksum does not match. Only when every array is written is
the directory renamed to ``MAP_DIR``, so a map package is either complete or absent.

With ``workers`` or ``scheduler`` the chunks are computed on a Dask cluster (local or
existing), one task per missing chunk; the driver still writes the package, so the result
is the same as the single-process build.

With a DSM/DEM the terrain (:mod:`orthonav.mapdb.dsm`) is attached before the rename too;
it is read, resampled and checked before any tile, so a wrong DSM fails before the long part
of the build.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import shutil
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import CancelledError
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from types import ModuleType
from typing import IO, TYPE_CHECKING

import cv2
import numpy as np
from tqdm import tqdm

from orthonav import __version__
from orthonav.atomic import atomic_path, sha256_file, write_npz_atomic, write_text_atomic
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, FeatureSet, Runtime, create_backend
from orthonav.geo import GeoGrid, GeoRaster, bounded_block_cache, bright_pixels
from orthonav.mapdb.dsm import PreparedTerrain, prepare_terrain, store_terrain
from orthonav.mapdb.globalindex import GLOBAL, METHODS, GlobalIndex, cnn_index, train_index
from orthonav.mapdb.package import (
    FEATURE_DIR,
    FORMAT,
    FORMAT_VERSION,
    MANIFEST,
    PREVIEW,
    TILES,
    MapPackage,
    check_replaceable,
    chunk_file,
    index_chunks,
    keypoint_dtype,
    write_chunk,
)
from orthonav.mapdb.tiling import TileLayout, TilingConfig, check_footprint, layout_tiles, work_gsd_m

if TYPE_CHECKING:
    from distributed import Client, Future, LocalCluster

log = logging.getLogger(__name__)

CHUNK_TILES = 32
PREVIEW_PX = 1024
BUILD_KEY = "build.json"
PROGRESS_DIR = "progress"  # in the work directory only: saved tiles and the seals of saved parts
# Keypoints this close to nodata or padding are dropped: the border itself is a strong edge.
BORDER_PX = 10
SCHEDULER_TIMEOUT_S = 10.0  # to reach an existing scheduler, and for it to have a worker
TASK_RETRIES = 2  # a failed chunk is tried this many more times before the build stops
_SCALE = "pip install 'orthonav[scale]'"


# Above this many tiles a build asks to be confirmed: it takes hours and gigabytes.
LARGE_MAP_TILES = 20_000
# ORB's measured build rate on 2 cores (docs, Scale): about 20 km^2/min at 0.5 m/px.
ORB_PIXELS_PER_S = 1.4e6
KEYPOINT_RECORD_BYTES = 44  # tile, tile px, map px, CRS x/y, score (keypoint_dtype) before the descriptor


def _large_map_message(
    raster: GeoRaster, grid: GeoGrid, tiles: int, features: FeatureBackend, limit: int
) -> str:
    """What a large build would cost, so that it is started knowingly."""
    empty = features.empty().descriptors
    per_keypoint = KEYPOINT_RECORD_BYTES + empty.dtype.itemsize * empty.shape[1]
    disk_gb = tiles * int(features.conf.get("max_keypoints", 1024)) * per_keypoint / 1e9
    hours = grid.width * grid.height / ORB_PIXELS_PER_S / 3600.0
    return (
        f"{raster.path}: {raster.width} x {raster.height} px, {grid.width} x {grid.height} px at the work "
        f"resolution: {tiles} tiles (more than {limit}), up to {disk_gb:.1f} GB of features and about "
        f"{hours:.1f} h with ORB on 2 cores (learned backends are slower); pass --yes to build it "
        "anyway, or crop the orthophoto to the area to be flown"
    )


@dataclass
class BuildReport:
    """What a build says as it goes (``say``: resuming, damaged parts built again) and what it did,
    for its summary: tiles reused from an interrupted build, tiles built by this one."""

    say: Callable[[str], object] = log.info
    reused: int = 0
    built: int = 0


def build_map(
    ortho_path: str | Path,
    out_dir: str | Path,
    camera: Camera,
    tiling: TilingConfig | None = None,
    backend: str = "orb",
    backend_conf: dict | None = None,
    overwrite: bool = False,
    progress: bool = True,
    runtime: Runtime | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    dsm: Path | None = None,
    max_tiles: int | None = LARGE_MAP_TILES,
    report: BuildReport | None = None,
) -> MapPackage:
    """Build (or resume building) a map package; returns it opened.

    ``runtime`` (device, threads) only decides where features are computed, so it is not
    part of the package: a map built on a GPU is used on the drone's CPU. ``workers`` runs
    the chunks on a local Dask cluster of that many processes, ``scheduler`` (an address)
    on an existing cluster whose workers see ``ortho_path`` and ``out_dir`` at the same paths.
    ``dsm``: a DSM/DEM GeoTIFF whose heights become the package's terrain. A map of more than
    ``max_tiles`` tiles is refused with its size, disk and time estimate until asked for
    (``max_tiles=None``, ``map build --yes``). ``report`` hears what the build says and counts
    the tiles it reused and built.
    """
    out_dir = Path(out_dir)
    report = report or BuildReport()
    with _sole_builder(out_dir):
        if out_dir.exists() and not overwrite:
            raise OrthonavError(f"{out_dir}: already exists (use --overwrite to replace it)")
        if out_dir.exists():
            check_replaceable(out_dir)
        features = create_backend(backend, runtime, **(backend_conf or {}))
        tiling = (tiling or TilingConfig()).for_backend(features.frame_budget_px)
        with (
            bounded_block_cache(),
            _dask_client(workers, scheduler) as client,
            GeoRaster(ortho_path) as raster,
        ):
            gsd = work_gsd_m(raster.gsd_m, camera, tiling)
            short_side_m = min(camera.nadir_footprint_m(tiling.nominal_alt_m))
            check_footprint(short_side_m, gsd, tiling.nominal_alt_m, "nominal altitude")
            factor = gsd / raster.gsd_m
            grid = raster.scaled(factor)
            layout = layout_tiles(grid.width, grid.height, gsd, camera, tiling)
            if max_tiles is not None and len(layout) > max_tiles:
                raise OrthonavError(_large_map_message(raster, grid, len(layout), features, max_tiles))
            preview = preview_rgb(raster)
            terrain = None if dsm is None else _prepare_terrain(Path(dsm), grid, preview)
            key = {
                "source": str(Path(ortho_path).resolve()),
                "source_sha256": sha256_file(raster.path),
                "camera": camera.to_dict(),
                "tiling": tiling.to_dict(),
                "features": {"backend": backend, "config": features.conf, "chunk_tiles": CHUNK_TILES},
                "format_version": FORMAT_VERSION,
            }
            partial = _prepare_partial(out_dir, key, report)
            source = _TileSource.of(raster, grid, features)
            _extract_chunks(raster, features, source, layout, partial, progress, client, report)
            _write_package(partial, raster, preview, grid, gsd, layout, key)
        if terrain is not None:
            store_terrain(MapPackage(partial), terrain)
        _publish(partial, out_dir)
        return MapPackage(out_dir)


@contextmanager
def _sole_builder(out_dir: Path) -> Iterator[None]:
    """One build of ``out_dir`` at a time, or an error at once naming the process building it:
    two would share ``MAP_DIR.partial`` and remove or rename it under each other (a second
    terminal, or a web server restarted while its first build's process lives on). The lock is
    the kernel's flock on ``MAP_DIR.lock`` (holding the builder's pid, removed when the build
    ends): it goes with its process however that ends, so a killed build leaves only the file,
    which the next build takes. No lock where there is no flock (Windows)."""
    if sys.platform == "win32":
        yield
        return
    import fcntl

    lock = out_dir.with_name(out_dir.name + ".lock")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(3):
        with open(lock, "a+") as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                handle.seek(0)
                holder = handle.read().strip() or "unknown"
                raise OrthonavError(
                    f"map build {out_dir}: another build (pid {holder}) is writing it, holding {lock}; "
                    "wait for it to end or stop it"
                ) from None
            if not _still_the_file(lock, handle):  # a build that ended removed the file after it was opened
                continue
            handle.truncate(0)
            handle.write(str(os.getpid()))
            handle.flush()
            try:
                yield
            finally:
                lock.unlink(missing_ok=True)
            return
    raise OrthonavError(f"map build {out_dir}: {lock} kept changing under this build; run it again")


def _still_the_file(path: Path, handle: IO) -> bool:
    """Whether ``path`` is still the file ``handle`` has open."""
    try:
        return os.path.samestat(os.stat(path), os.fstat(handle.fileno()))
    except FileNotFoundError:
        return False


def _prepare_terrain(dsm: Path, grid: GeoGrid, preview: np.ndarray) -> PreparedTerrain:
    """The DSM's heights on the map, checked before any tile is built."""
    return prepare_terrain(dsm, grid, (preview, grid.scaled(grid.width / preview.shape[1])))


def _prepare_partial(out_dir: Path, key: dict, report: BuildReport) -> Path:
    """The work directory; kept (resume) only when it was started with the same settings, else
    started again, said so (a rerun with another option does not resume)."""
    partial = out_dir.with_name(out_dir.name + ".partial")
    key_file = partial / BUILD_KEY
    if partial.exists():
        try:
            same = json.loads(key_file.read_text()) == json.loads(json.dumps(key))
        except (OSError, json.JSONDecodeError):
            same = False
        if not same:
            report.say(
                f"map build: {partial} was started with other settings or another source; starting again"
            )
            shutil.rmtree(partial)
    if not partial.exists():
        partial.mkdir(parents=True)
        write_text_atomic(key_file, json.dumps(key, indent=2))
    for folder in (FEATURE_DIR, PROGRESS_DIR):
        (partial / folder).mkdir(exist_ok=True)
    return partial


@dataclass(frozen=True)
class _Chunk:
    """Consecutive tiles (their work-pixel boxes), the file they are gathered into, and the
    folder where each tile is saved until then; ``saved``: tiles found saved at the start."""

    start: int
    boxes: np.ndarray
    file: Path
    progress: Path
    saved: int = 0

    def tile_file(self, tile: int) -> Path:
        return self.progress / f"tile_{tile:07d}.npy"

    @property
    def label(self) -> str:
        return f"chunk {self.file.name} (tiles {self.start}-{self.start + len(self.boxes) - 1})"


@dataclass(frozen=True)
class _TileSource:
    """How to compute tiles' features, in a form that pickles: open rasters and feature
    backends do not, so a Dask worker opens the raster by path and creates the backend."""

    path: Path
    grid: GeoGrid  # the work grid
    backend: str
    conf: dict
    runtime: Runtime

    @staticmethod
    def of(raster: GeoRaster, grid: GeoGrid, features: FeatureBackend) -> _TileSource:
        return _TileSource(raster.path.resolve(), grid, features.name, features.conf, features.runtime)


def _extract_chunks(
    raster: GeoRaster,
    features: FeatureBackend,
    source: _TileSource,
    layout: TileLayout,
    partial: Path,
    progress: bool,
    client: Client | None,
    report: BuildReport,
) -> None:
    """Compute and save the tiles not saved yet, here or on the Dask cluster. The bar moves per
    tile here (a chunk of a large learned backend takes minutes) and per chunk on Dask."""
    pending = _pending_chunks(layout, partial, features, report)
    report.reused = len(layout) - sum(len(chunk.boxes) - chunk.saved for chunk in pending)
    report.built = len(layout) - report.reused
    if report.reused:
        report.say(f"resuming: {report.reused} of {len(layout)} tiles already built (in {partial})")
    with tqdm(
        total=len(layout), initial=report.reused, desc="map build", unit="tile", disable=not progress
    ) as bar:
        if client is not None:
            _extract_on_dask(client, source, pending, bar)
            return
        for chunk in pending:
            _compute_chunk(raster, source, features, chunk, on_tile=bar.update)


def _pending_chunks(
    layout: TileLayout, partial: Path, features: FeatureBackend, report: BuildReport
) -> list[_Chunk]:
    """The chunks not complete yet, each with the count of its tiles already saved: a resumed
    build skips the rest. A saved part that fails its check is removed, to be built again, and
    said so in one line."""
    dtype = _record_dtype(features)
    chunks: list[_Chunk] = []
    damaged: list[tuple[Path, str, range]] = []
    for start in range(0, len(layout), CHUNK_TILES):
        chunk = _Chunk(
            start,
            layout.boxes[start : start + CHUNK_TILES],
            chunk_file(partial / FEATURE_DIR, start),
            partial / PROGRESS_DIR,
        )
        if _reusable(chunk.file, chunk.progress, dtype, range(start, start + len(chunk.boxes)), damaged):
            continue
        saved = sum(
            _reusable(chunk.tile_file(tile), chunk.progress, dtype, range(tile, tile + 1), damaged)
            for tile in range(start, start + len(chunk.boxes))
        )
        chunks.append(replace(chunk, saved=saved))
    if damaged:
        tiles = sum(len(part) for _, _, part in damaged)
        shown = "; ".join(f"{file.name} {problem}" for file, problem, _ in damaged[:3])
        more = f"; and {len(damaged) - 3} more" if len(damaged) > 3 else ""
        report.say(
            f"map build: {len(damaged)} saved part(s) of the interrupted build damaged ({shown}{more}); "
            f"building their {tiles} tile(s) again"
        )
    return chunks


def _seal_file(file: Path, progress: Path) -> Path:
    return progress / f"{file.name}.sha256"


def _save_sealed(file: Path, records: np.ndarray, progress: Path) -> None:
    """Save records atomically, then their checksum: a part without a matching seal is not reused."""
    write_chunk(file, records)
    write_text_atomic(_seal_file(file, progress), sha256_file(file))


def _reusable(
    file: Path, progress: Path, dtype: np.dtype, tiles: range, damaged: list[tuple[Path, str, range]]
) -> bool:
    """Whether a saved part (a chunk, or one tile) can be reused. One without a seal was cut
    short by the interruption; one whose seal or records do not match is damaged, and added to
    ``damaged``. Either is removed, with its seal, to be built again."""
    if not file.exists():
        return False
    seal = _seal_file(file, progress)
    problem = None
    try:
        if not seal.exists():
            file.unlink()
            return False
        if seal.read_text().strip() != sha256_file(file):
            problem = "checksum mismatch"
        else:
            records = np.load(file, mmap_mode="r", allow_pickle=False)
            if records.dtype != dtype or not np.isin(records["tile"], tiles).all():
                problem = "not this build's records"
    except (OSError, ValueError) as exc:
        problem = f"unreadable ({exc})"
    if problem is None:
        return True
    damaged.append((file, problem, tiles))
    file.unlink(missing_ok=True)
    seal.unlink(missing_ok=True)
    return False


def _record_dtype(features: FeatureBackend) -> np.dtype:
    return keypoint_dtype(features.descriptor_dtype, features.descriptor_size)


def _compute_chunk(
    raster: GeoRaster,
    source: _TileSource,
    features: FeatureBackend,
    chunk: _Chunk,
    on_tile: Callable[[], object] | None = None,
) -> None:
    """The one chunk computation, shared by the single-process build and the Dask tasks: each
    tile not saved yet is computed and saved, then the chunk's tiles are gathered into its file
    and the tiles' files removed; ``on_tile`` is called as each tile is done (a progress bar's
    update)."""
    parts = []
    for tile, box in enumerate(chunk.boxes, chunk.start):
        file = chunk.tile_file(tile)
        if file.exists():
            parts.append(np.load(file, allow_pickle=False))
            continue
        found = _tile_features(raster, source.grid, box, features)
        records = _tile_records(found, tile, box, source.grid, _record_dtype(features))
        _save_sealed(file, records, chunk.progress)
        parts.append(records)
        if on_tile is not None:
            on_tile()
    _save_sealed(chunk.file, np.concatenate(parts), chunk.progress)
    for tile in range(chunk.start, chunk.start + len(chunk.boxes)):
        chunk.tile_file(tile).unlink(missing_ok=True)
        _seal_file(chunk.tile_file(tile), chunk.progress).unlink(missing_ok=True)


def _tile_features(raster: GeoRaster, grid: GeoGrid, box: np.ndarray, features: FeatureBackend) -> FeatureSet:
    rgb = raster.read_grid_box(grid, box)
    valid = bright_pixels(rgb).astype(np.uint8)
    mask = cv2.erode(valid, np.ones((2 * BORDER_PX + 1, 2 * BORDER_PX + 1), np.uint8))
    if not mask.any():
        return features.empty()
    return features.extract(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), mask)


# --- Dask ---------------------------------------------------------------------------------------


@contextmanager
def _dask_client(workers: int | None, scheduler: str | None) -> Iterator[Client | None]:
    """No client for the single-process build; else one of a new local cluster or of an
    existing one, connected before any work so that a bad address fails at once."""
    if workers is None and scheduler is None:
        yield None
        return
    if workers is not None and workers < 1:
        raise OrthonavError(f"workers: expected a positive count, got {workers}")
    distributed = _import_distributed()
    if scheduler is not None:
        with _connect(distributed, scheduler, workers or 1) as client:
            yield client
        return
    try:
        cluster = _local_cluster(distributed, workers)
    except (OSError, RuntimeError) as exc:
        raise OrthonavError(f"could not start a local Dask cluster of {workers} workers: {exc}") from exc
    with cluster, distributed.Client(cluster) as client:
        yield client


def _local_cluster(distributed: ModuleType, workers: int) -> LocalCluster:
    """One single-threaded process per worker, no dashboard. Dask's default
    MALLOC_TRIM_THRESHOLD_ for workers (memory handed back to the OS eagerly) makes the
    many short-lived tile arrays slower to allocate, so it is left to glibc here."""
    import dask

    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        return distributed.LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        )


def _import_distributed() -> ModuleType:
    try:
        import distributed
    except ImportError:
        raise OrthonavError(f"a distributed map build needs Dask: {_SCALE}") from None
    return distributed


def _connect(distributed: ModuleType, address: str, workers: int) -> Client:
    """A client of the scheduler at ``address`` that has at least ``workers`` workers."""
    try:
        client = distributed.Client(address, timeout=SCHEDULER_TIMEOUT_S)
    except Exception as exc:  # refused, timed out, a bad address, or a peer that is not Dask
        raise OrthonavError(
            f"Dask scheduler {address}: cannot be reached ({type(exc).__name__}: {exc}); "
            "is it running, and is this its address (tcp://HOST:PORT)?"
        ) from None
    try:
        client.wait_for_workers(workers, timeout=SCHEDULER_TIMEOUT_S)
    except (OSError, TimeoutError) as exc:
        client.close()
        raise OrthonavError(
            f"Dask scheduler {address}: has fewer than {workers} worker(s) after "
            f"{SCHEDULER_TIMEOUT_S:g} s ({exc})"
        ) from None
    return client


def _extract_on_dask(client: Client, source: _TileSource, chunks: list[_Chunk], bar: tqdm) -> None:
    """One task per chunk, retried; the first chunk that still fails stops the build (the
    chunks saved so far stay for the next run)."""
    from distributed import as_completed

    # Learned backends: one torch thread per worker unless asked, the workers share the cores.
    source = replace(source, runtime=replace(source.runtime, threads=source.runtime.threads or 1))
    build_id = uuid.uuid4().hex[:8]
    futures = {
        client.submit(
            _chunk_task, source, chunk, key=f"orthonav-{chunk.file.stem}-{build_id}", retries=TASK_RETRIES
        ): chunk
        for chunk in chunks
    }
    for future in as_completed(futures):
        chunk = futures[future]
        if future.status != "finished":
            cause = _failure(future)
            client.cancel(list(futures))
            raise OrthonavError(
                f"map build: {chunk.label} failed after {1 + TASK_RETRIES} attempts: {cause}; "
                f"the chunks saved in {chunk.file.parent} are kept, run the build again to resume"
            )
        bar.update(len(chunk.boxes) - chunk.saved)


def _failure(future: Future) -> str:
    """What went wrong in a task, as one line (a lost or cancelled task has no exception)."""
    try:
        exc = future.exception()
    except (Exception, CancelledError) as lost:
        exc = lost
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


_worker_state = threading.local()


def _chunk_task(source: _TileSource, chunk: _Chunk) -> int:
    """A Dask task: compute and save one chunk on the worker; returns its tile count."""
    raster, features = _worker_tools(source)
    with bounded_block_cache():
        _compute_chunk(raster, source, features, chunk)
    return len(chunk.boxes)


def _worker_tools(source: _TileSource) -> tuple[GeoRaster, FeatureBackend]:
    """The raster and backend, opened once per worker thread and build rather than per chunk:
    reopening loses GDAL's block cache, learned backends load weights, and OpenCV objects are
    not safe to share between threads."""
    stat = source.path.stat()
    key = (
        source.path,
        stat.st_mtime_ns,
        stat.st_size,
        source.backend,
        json.dumps(source.conf),
        source.runtime,
    )
    cached = getattr(_worker_state, "tools", None)
    if cached is None or cached[0] != key:
        if cached is not None:
            cached[1].close()
        raster = GeoRaster(source.path)
        cached = _worker_state.tools = (
            key,
            raster,
            create_backend(source.backend, source.runtime, **source.conf),
        )
    return cached[1], cached[2]


def _tile_records(
    features: FeatureSet, tile: int, box: np.ndarray, grid: GeoGrid, dtype: np.dtype
) -> np.ndarray:
    """One tile's keypoints as the records of a feature chunk (``dtype``: :func:`keypoint_dtype`)."""
    records = np.zeros(len(features), dtype)
    records["tile"] = tile
    records["tile_px"] = features.keypoints
    # Feature backends give OpenCV pixels (centre of pixel 0 at 0); work px put it at 0.5.
    records["map_px"] = records["tile_px"] + 0.5 + box[:2]
    x, y = grid.pixel_to_crs(records["map_px"][:, 0], records["map_px"][:, 1])
    records["crs"] = np.column_stack([x, y])
    records["score"] = features.scores
    records["descriptor"] = features.descriptors
    return records


def _write_package(
    partial: Path,
    raster: GeoRaster,
    preview: np.ndarray,
    grid: GeoGrid,
    gsd: float,
    layout: TileLayout,
    key: dict,
) -> None:
    chunks = index_chunks(partial / FEATURE_DIR, len(layout), CHUNK_TILES)
    if chunks["feature_offsets"][-1] == 0:
        raise OrthonavError(
            f"{raster.path}: no features found anywhere in the orthophoto; it has no texture to navigate by"
        )
    write_npz_atomic(partial / TILES, **_tile_arrays(grid, layout), **chunks)
    preview_shape = write_preview(partial / PREVIEW, raster, preview)
    manifest = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "orthonav_version": __version__,
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "source": {
            "path": key["source"],
            "sha256": key["source_sha256"],
            "width": raster.width,
            "height": raster.height,
            "bands": raster.band_count,
            "dtype": raster.dtype,
            "gsd_m": raster.gsd_m,
            "transform": list(raster.transform)[:6],
        },
        "work": {
            "crs_wkt": grid.crs.to_wkt(),
            "transform": list(grid.transform)[:6],
            "width": grid.width,
            "height": grid.height,
            "gsd_m": gsd,
        },
        "camera": key["camera"],
        "tiling": key["tiling"],
        "tiling_layout": {
            "tile_px": layout.tile_px,
            "stride_px": layout.stride_px,
            "rows": layout.rows,
            "cols": layout.cols,
            "count": len(layout),
        },
        "features": key["features"],
        "preview": {"width": preview_shape[1], "height": preview_shape[0]},
        "arrays": {TILES: sha256_file(partial / TILES)},
    }
    write_text_atomic(partial / MANIFEST, json.dumps(manifest, indent=2))


def _tile_arrays(grid: GeoGrid, layout: TileLayout) -> dict[str, np.ndarray]:
    boxes = layout.boxes
    cols = np.stack([boxes[:, 0], boxes[:, 2], (boxes[:, 0] + boxes[:, 2]) / 2], 1)
    rows = np.stack([boxes[:, 1], boxes[:, 3], (boxes[:, 1] + boxes[:, 3]) / 2], 1)
    lat, lon = grid.pixel_to_latlon(cols, rows)
    grid_rc = np.stack(np.divmod(np.arange(len(layout)), layout.cols), 1)
    return {
        "box_px": boxes,
        "grid_rc": grid_rc,
        "padded": layout.padded,
        "corners_latlon": np.stack([lat, lon], -1),
    }


def preview_rgb(raster: GeoRaster) -> np.ndarray:
    """The orthophoto at <= PREVIEW_PX, RGB."""
    scale = max(1.0, max(raster.width, raster.height) / PREVIEW_PX)
    shape = (max(1, round(raster.height / scale)), max(1, round(raster.width / scale)))
    return raster.read_rgb(out_shape=shape)


def write_preview(file: Path, raster: GeoRaster, rgb: np.ndarray | None = None) -> tuple[int, int]:
    """The orthophoto at <= PREVIEW_PX for plots (``rgb``: already read); returns its (height, width)."""
    rgb = preview_rgb(raster) if rgb is None else rgb
    with atomic_path(file) as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 85])
    return rgb.shape[0], rgb.shape[1]


def _publish(partial: Path, out_dir: Path) -> None:
    """Swap the finished build into place; an old package is removed only after the swap."""
    (partial / BUILD_KEY).unlink()
    shutil.rmtree(partial / PROGRESS_DIR)
    old = out_dir.with_name(out_dir.name + ".old")
    if out_dir.exists():
        if old.exists():
            shutil.rmtree(old)
        os.replace(out_dir, old)
    os.replace(partial, out_dir)
    if old.exists():
        shutil.rmtree(old)


def build_global_index(
    package: MapPackage,
    words: int = 32,
    seed: int = 0,
    method: str = "vlad",
    model: str | None = None,
    progress: bool = False,
) -> MapPackage:
    """Make the re-localization index, store it, reopen: ``vlad`` trains on the package's own
    features; ``cnn`` describes each tile of the orthophoto with a retrieval model (``model``:
    a file path, default the one shipped with orthonav)."""
    if method == "vlad":
        index = train_index(
            lambda tile: package.tile_records(tile)["descriptor"], package.feature_offsets, words, seed
        )
        config = {"method": "vlad", "words": words, "seed": seed}
    elif method == "cnn":
        model = str(Path(model).resolve()) if model else None
        index = cnn_index(package.source_path, package.grid, package.tiles.box_px, model, progress)
        config = {"method": "cnn", "model": index.model, "model_sha256": index.model_sha256}
    else:
        raise OrthonavError(f"global index method {method!r}: expected one of {', '.join(METHODS)}")
    write_global_index(package, index, config)
    return MapPackage(package.path)


def write_global_index(package: MapPackage, index: GlobalIndex, config: dict) -> None:
    """``global.npz`` and its manifest record, each written atomically."""
    index.write(package.path / GLOBAL)
    record = {**config, "file": GLOBAL, "sha256": sha256_file(package.path / GLOBAL)}
    write_text_atomic(
        package.path / MANIFEST, json.dumps({**package.manifest, "global_index": record}, indent=2)
    )
