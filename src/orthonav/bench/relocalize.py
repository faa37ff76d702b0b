"""``orthonav bench relocalize``: finding a lost frame on maps of growing size, index vs all tiles.

Maps are mosaics of real NAIP imagery (:mod:`orthonav.bench.mosaic`) of 2 to 24 blocks
(8 to 100 km^2) from every date but the last, built with the chosen backend at the chosen
altitude and indexed (:mod:`orthonav.mapdb.globalindex`). Frames at random places and
headings are rendered from the map's mosaic itself (same-date) and from the same layout with
every block drawn from the last date, which is in no block of the map (cross-date). The
vehicle is lost: altitude, compass heading and attitude only. Measured side by side: recall@k
of the tile under the drone, and the share of frames fixed within 25 m and the time per frame
when matching the index's top tiles versus every tile, for each index method (``vlad``,
``cnn``) on the same frames. Every ground is in the map once per date, so besides recall of the
tile under the drone, "any copy" counts a top k holding that ground in any block (any date).
Fix sources side by side on the same frames: the keypoint localizer (``keypoints``), the
dense-correlation ``Corrector`` searching the index's top tiles (``correlation``) and the cascade
(``cascade``: its candidates from the index, coarse, fine, verification, acceptance); an accepted
fix farther than 25 m from the truth is counted as wrong, and among those, one within 25 m of
the same ground in another block ("at a copy") is counted apart too.
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.bench.mosaic import Mosaic, mosaic_layout, write_mosaic
from orthonav.bench.scoring import error_m, median, share
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize import Cascade, CorrectionConfig, Corrector, Localizer, LocalizerConfig
from orthonav.mapdb import MapPackage, TilingConfig, build_global_index, build_map
from orthonav.mapdb.globalindex import METHODS
from orthonav.types import FixSource, Prior
from orthonav.viz.relocalize import plot_relocalize_bench

FIXED_WITHIN_M = 25.0
FIX_SOURCES = ("keypoints", "correlation", "cascade")


@dataclass(frozen=True)
class RelocalizeBenchConfig:
    """Everything that decides the numbers; written beside them."""

    blocks: tuple[int, ...] = (2, 6, 12, 24)
    frames: int = 20
    alt_m: float = 1000.0
    features: str = "orb"
    words: int = 32
    indexes: tuple[str, ...] = ("vlad",)  # global index methods, side by side on the same frames
    candidates: int = 10
    recall_at: tuple[int, ...] = (1, 5, 10)
    photometric: float = 0.6
    seed: int = 0
    all_tiles: bool = True  # also match every tile (slow with learned backends on big maps)
    fix_sources: tuple[str, ...] = ("keypoints",)  # keypoints, correlation (dense), cascade

    def __post_init__(self) -> None:
        if not self.blocks or min(self.blocks) < 1 or self.frames < 1:
            raise OrthonavError(f"bench relocalize: expected blocks >= 1 and frames >= 1, got {self}")
        if not self.indexes or not set(self.indexes) <= set(METHODS):
            raise OrthonavError(
                f"bench relocalize indexes {self.indexes}: expected some of {', '.join(METHODS)}"
            )
        if not self.fix_sources or not set(self.fix_sources) <= set(FIX_SOURCES):
            raise OrthonavError(
                f"bench relocalize fix sources {self.fix_sources}: expected some of {', '.join(FIX_SOURCES)}"
            )


def run_relocalize_benchmark(
    sources: list[Path], out_json: Path, config: RelocalizeBenchConfig, progress: bool = True
) -> dict:
    """Every map size, same-date and cross-date frames; JSON and a PNG written beside ``out_json``."""
    watch = LoadWatch()
    if len(sources) < 2:
        raise OrthonavError(
            f"bench relocalize: needs at least two dates of the area (the last one gives the "
            f"cross-date frames), got {len(sources)} GeoTIFF(s)"
        )
    camera = Camera.from_hfov(640, 480, 60.0)
    rows = []
    with tempfile.TemporaryDirectory(prefix="orthonav-bench-relocalize-") as tmp:
        for blocks in config.blocks:
            mosaic = mosaic_layout(sources[:-1], blocks)
            map_tif = write_mosaic(mosaic, Path(tmp) / f"map_{blocks}.tif")
            started = time.perf_counter()
            tiling = TilingConfig(nominal_alt_m=config.alt_m)
            package = build_map(
                map_tif, Path(tmp) / f"map_{blocks}", camera, tiling, config.features, progress=False
            )
            build_s = time.perf_counter() - started
            size = {"blocks": blocks, "km2": _area_km2(map_tif, mosaic), "tiles": len(package)}
            for i, method in enumerate(config.indexes):
                started = time.perf_counter()
                package = build_global_index(package, config.words, config.seed, method)
                timing = {"build_s": round(build_s, 1), "index_s": round(time.perf_counter() - started, 1)}
                for condition, every_block_from in (("same-date", None), ("cross-date", sources[-1])):
                    frames_tif = Path(tmp) / f"frames_{blocks}_{condition}.tif"
                    if not frames_tif.exists():
                        write_mosaic(mosaic, frames_tif, every_block_from)
                    desc = f"{blocks} blocks {condition} {method}"
                    # Matching every tile does not depend on the index: measured with the first only.
                    all_tiles = config.all_tiles and i == 0
                    row = _evaluate(
                        package, map_tif, frames_tif, mosaic, camera, config, all_tiles, progress, desc
                    )
                    rows.append({**size, "index": method, "condition": condition, **timing, **row})
    result = {
        "config": asdict(config),
        "sources": [str(p) for p in sources],
        "rows": rows,
        "machine": watch.record(),
    }
    write_json_atomic(out_json, result)
    plot_relocalize_bench(rows, config.recall_at, out_json.with_suffix(".png"))
    return result


def _area_km2(mosaic_tif: Path, mosaic: Mosaic) -> float:
    with GeoRaster(mosaic_tif) as raster:
        return round(mosaic.area_km2(raster.gsd_m), 1)


def _evaluate(
    package: MapPackage,
    map_tif: Path,
    frames_tif: Path,
    mosaic: Mosaic,
    camera: Camera,
    config: RelocalizeBenchConfig,
    all_tiles: bool,
    progress: bool,
    desc: str,
) -> dict:
    rng = np.random.default_rng(config.seed)
    index_localizer = Localizer(package, camera, LocalizerConfig(global_candidates=config.candidates))
    localizers: dict[str, FixSource] = {}
    if "keypoints" in config.fix_sources:
        localizers["index"] = index_localizer
        if all_tiles:
            localizers["all tiles"] = Localizer(package, camera, LocalizerConfig(global_candidates=0))
    with GeoRaster(frames_tif) as frames, GeoRaster(map_tif) as map_raster:
        if "correlation" in config.fix_sources:
            # Gradient correlation against the map's orthophoto around the index's top tiles.
            localizers["correlation"] = Corrector(map_raster, camera, CorrectionConfig(), package=package)
        if "cascade" in config.fix_sources:
            localizers["cascade"] = Cascade(package, map_raster, camera)
        ranks, copy_ranks, outcomes = [], [], {name: [] for name in localizers}
        for _ in tqdm(range(config.frames), desc=desc, disable=not progress, leave=False):
            truth, block, offset = _random_pose(frames, mosaic, config.alt_m, rng)
            frame = render_frame(frames, camera, truth, Photometric.random(rng, config.photometric), rng)
            prior = Prior(alt_agl_m=truth.alt_agl_m, heading_deg=truth.yaw_deg, pitch_deg=0.0, roll_deg=0.0)
            found, _ = package.global_index.search(
                index_localizer.frame_view(frame, prior), max(config.recall_at)
            )
            ranks.append(_first_rank(found, set(package.tiles_within(truth.lat, truth.lon, 0.0).tolist())))
            copies = _copies_latlon(frames, mosaic, block, offset)
            copy_ranks.append(_first_rank(found, _tiles_under(package, copies)))
            for name, localizer in localizers.items():
                outcomes[name].append(_relocalize(localizer, frame, prior, truth, copies))
    row = {}
    for label, found_ranks in (("", ranks), (" any copy", copy_ranks)):
        for k in config.recall_at:
            hits = [r is not None and r < k for r in found_ranks]
            row[f"recall@{k}{label}"] = share(hits, len(hits))
    for name, results in outcomes.items():
        n = len(results)
        row[f"fixed {name}"] = share((outcome == "fixed" for outcome, _ in results), n)
        row[f"wrong {name}"] = share((outcome in ("copy", "wrong") for outcome, _ in results), n)
        row[f"at a copy {name}"] = share((outcome == "copy" for outcome, _ in results), n)
        row[f"ms {name}"] = median(ms for _, ms in results)
    return row


def _first_rank(found: np.ndarray, right: set[int]) -> int | None:
    return next((r for r, tile in enumerate(found) if tile in right), None)


def _copies_latlon(
    raster: GeoRaster, mosaic: Mosaic, block: int, offset: tuple[float, float]
) -> list[tuple[float, float]]:
    """The same ground in every block cut from the same quarter (any date, this block included)."""
    this = mosaic.blocks[block]
    copies = []
    for i, other in enumerate(mosaic.blocks):
        if (other.quarter, other.mirror) == (this.quarter, this.mirror):
            col0, row0 = mosaic.origin_px(i)
            lat, lon = raster.pixel_to_latlon(col0 + offset[0], row0 + offset[1])
            copies.append((float(lat), float(lon)))
    return copies


def _tiles_under(package: MapPackage, places: list[tuple[float, float]]) -> set[int]:
    return {int(t) for lat, lon in places for t in package.tiles_within(lat, lon, 0.0)}


def _random_pose(
    raster: GeoRaster, mosaic: Mosaic, alt_m: float, rng: np.random.Generator
) -> tuple[TruePose, int, tuple[float, float]]:
    """Over a random block (not an empty cell of the grid), a quarter block from its edges;
    also the block and the pixel offset in it."""
    block = int(rng.integers(len(mosaic.blocks)))
    col0, row0 = mosaic.origin_px(block)
    bw, bh = mosaic.block_px
    offset = (rng.uniform(0.25, 0.75) * bw, rng.uniform(0.25, 0.75) * bh)
    lat, lon = raster.pixel_to_latlon(col0 + offset[0], row0 + offset[1])
    pose = TruePose(float(lat), float(lon), alt_m, float(rng.uniform(0.0, 360.0)), 0.0, 0.0)
    return pose, block, offset


def _relocalize(
    source: FixSource, frame: np.ndarray, prior: Prior, truth: TruePose, copies: list[tuple[float, float]]
) -> tuple[str, float]:
    """("fixed" within 25 m; "copy": accepted within 25 m of the same ground in another block;
    "wrong": accepted elsewhere; or "rejected"), milliseconds."""
    started = time.perf_counter()
    fix = source.localize(frame, prior)
    ms = 1000.0 * (time.perf_counter() - started)
    if not fix.accepted:
        return "rejected", ms
    if error_m(truth.lat, truth.lon, fix.pose.lat, fix.pose.lon) <= FIXED_WITHIN_M:
        return "fixed", ms
    near_copy = min(float(distance_m(fix.pose.lat, fix.pose.lon, *c)) for c in copies) <= FIXED_WITHIN_M
    return ("copy" if near_copy else "wrong"), ms
