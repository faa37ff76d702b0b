"""``orthonav bench speed``: every backend under every engine it has, side by side on the same
frames: time per stage, frames per second, peak memory and the accuracy that time buys.

Two datasets, as the localizer meets them:
- NAIP: 640 x 480 frames rendered at 1000 m from one year's orthophoto, localized with a 200 m
  prior on a map of the same year (same-date) and of another (cross-date);
- real drone photos (a folder laid out like ``../shared/data/real/seneca``), spread over the
  flight, on the DSM with the EXIF prior: decoding the JPEG is timed too.

Beside ORB, a ``baseline`` row: the simplest ORB loop (orthonav.bench.plainloop: tiles, brute
force with a ratio test, RANSAC homography, no checks) on the same NAIP frames and map, a
reference for time and for what the checks buy, never a fix source. Every row reports each
stage's p50 / p95 / p99 / max over the frames (``tails_ms``) beside its medians.

Each backend and engine runs in a process of its own, so that its peak memory (the high-water
mark of the resident set) and its thread pools are its own; the maps are built first, in
another process, and shared by the engines (the features are the same). Optionally the
companion loop (sim vehicle over UDP) gives the capture-to-message latency and dropped frames.
The ``cuda`` engine is torch on the GPU (the learned backends' extraction and matching; the rest
of the localizer stays on the CPU); where there is none it is a clear error, not a CPU run.
"""

from __future__ import annotations

import itertools
import os
import resource
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from contextlib import ExitStack
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from orthonav.atomic import write_json_atomic
from orthonav.bench.localize import (
    FALSE_FIX_M,
    LocalizeBenchConfig,
    build_bench_map,
    evaluate_samples,
    render_samples,
)
from orthonav.bench.machine import LoadWatch
from orthonav.bench.plainloop import PlainFix, PlainTileLoop
from orthonav.bench.real import RealBenchConfig, dataset_map, make_prior, metrics, read_queries, score
from orthonav.bench.scoring import error_m, mean, median, share, stage_tails, within_rates, wrong_rate
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, Runtime, available_backends, backend_class, onnx_backends
from orthonav.frames import load_frame
from orthonav.geo import GeoRaster
from orthonav.localize import (
    CASCADE,
    DEFAULT_COARSE_BACKBONE,
    KEYPOINTS,
    LocalizerConfig,
    coarse_backbones,
    make_fix_source,
    warm_up,
)
from orthonav.mapdb import MapPackage, check_max_frame_px
from orthonav.types import Fix, Prior
from orthonav.viz.speed import plot_speed_bench

CLASSICAL = ("orb", "sift")
# ``onnx-int8``: ONNX Runtime's int8 graph, where a backend has one (ALIKED's).
ENGINES = ("torch", "onnx", "onnx-int8", "cuda")
# The fix sources that match a backend's keypoints: alone, or as the cascade's fine stage.
FIX_SOURCES = (KEYPOINTS, CASCADE)
STAGES = (
    "decode_ms",
    "warp_ms",
    "extract_ms",
    "match_ms",
    "pose_ms",
    "coarse_ms",
    "fine_ms",
    "verify_ms",
    "refine_ms",
)
# The plain tile loop's row (its fix source): ORB's reference, measured where ORB is.
BASELINE = "baseline"
# What each NAIP condition reports of its accuracy, as shares of all frames: false fixes are
# more than FALSE_FIX_M off (orthonav's position; the plain loop's frame centre, all it gives).
NAIP_ACCURACY = (
    "fix_rate",
    "within_10m",
    "centre_within_10m",
    "within_25m",
    "centre_within_25m",
    "false_fix_rate",
)
# Where the loop's simulated camera takes its frames: the map's own orthophoto, or the cross-date one.
LATENCY_FRAMES = ("same-date", "cross-date")


@dataclass(frozen=True)
class SpeedBenchConfig:
    """What runs side by side, on how much data; written beside the numbers."""

    features: tuple[str, ...] = ("orb", "aliked")
    engines: tuple[str, ...] = ("torch", "onnx", "onnx-int8")
    fix_sources: tuple[str, ...] = (KEYPOINTS,)
    frames: int = 8  # NAIP frames per condition
    photos: int = 12  # real photos, spread evenly over the flight
    map_year: str = "2020"  # the NAIP orthophoto whose name holds this is the map
    frames_year: str = "2015"  # ... and this one gives the cross-date frames
    latency_s: float = 0.0  # seconds of companion loop per run; 0 skips it
    latency_frames: str = "same-date"  # one of LATENCY_FRAMES
    # The cascade's coarse correlations (fly's --coarse-backbone), each a run of its own.
    coarse_backbones: tuple[str, ...] = (DEFAULT_COARSE_BACKBONE,)
    seed: int = 0
    max_frame_px: int | None = None  # the photos' map: map build --max-frame-px (None: the backend's)
    baseline: bool = True  # the plain tile loop beside ORB (it reads ORB's map)

    def __post_init__(self) -> None:
        unknown = set(self.features) - set(available_backends())
        if unknown or not self.features:
            known = ", ".join(available_backends())
            raise OrthonavError(f"bench speed features {sorted(unknown)}: expected names from {known}")
        if not self.engines or set(self.engines) - set(ENGINES):
            raise OrthonavError(
                f"bench speed engines {list(self.engines)}: expected some of {', '.join(ENGINES)}"
            )
        if not self.fix_sources or set(self.fix_sources) - set(FIX_SOURCES):
            raise OrthonavError(
                f"bench speed fix sources {list(self.fix_sources)}: expected some of {', '.join(FIX_SOURCES)}"
            )
        check_max_frame_px(self.max_frame_px, "bench speed max frame size (--max-frame-px)")
        if self.latency_frames not in LATENCY_FRAMES:
            raise OrthonavError(
                f"bench speed latency frames {self.latency_frames!r}: expected one of "
                f"{', '.join(LATENCY_FRAMES)}"
            )
        if not self.coarse_backbones:
            raise OrthonavError("bench speed coarse backbones: expected at least one (e.g. gradient)")
        for spec in self.coarse_backbones:
            coarse_backbones(spec)
        if self.frames < 1 or self.photos < 0:
            raise OrthonavError(
                f"bench speed: frames >= 1 and photos >= 0, got {self.frames} and {self.photos}"
            )
        engineless = [n for n in self.features if n not in {name for name, _ in self.runs()}]
        if engineless:
            raise OrthonavError(
                f"bench speed: {', '.join(engineless)} has none of the engines {', '.join(self.engines)} "
                f"(ONNX Runtime runs {', '.join(onnx_backends())})"
            )

    def runs(self) -> list[tuple[str, str]]:
        """(backend, engine) pairs: the classical backends once (OpenCV), the learned ones under
        each asked engine they have."""
        out = []
        for name in self.features:
            if name in CLASSICAL:
                out.append((name, "opencv"))
            else:
                out += [(name, e) for e in self.engines if _has_engine(name, e)]
        return out

    def measured(self) -> list[tuple[str, str, str, str | None]]:
        """(backend, engine, fix source, coarse backbone) of every run: the cascade once per coarse
        backbone, the keypoints alone with none."""
        return [
            (name, engine, source, backbone)
            for (name, engine), source in itertools.product(self.runs(), self.fix_sources)
            for backbone in (self.coarse_backbones if source == CASCADE else (None,))
        ]


def _has_engine(name: str, engine: str) -> bool:
    """Whether learned backend ``name`` runs on ``engine``."""
    if engine == "torch" or engine == "cuda":
        return True
    if name not in onnx_backends():
        return False
    return engine == "onnx" or "int8" in backend_class(name, "onnx").precisions


@dataclass(frozen=True)
class _Data:
    naip_map: Path
    naip_frames: Path
    real: Path | None
    maps: Path


def run_speed_benchmark(
    naip_dir: Path,
    real_dir: Path | None,
    out: Path,
    config: SpeedBenchConfig = SpeedBenchConfig(),
    progress: Callable[[str], None] | None = None,
) -> dict:
    """Every (backend, engine) run, one process each; JSON and PNG written beside ``out``."""
    watch = LoadWatch()
    data = _Data(*_naip_pair(naip_dir, config), _real(real_dir), out.parent / f"{out.stem}_maps")
    builds = {}
    for name in config.features:
        if progress:
            progress(f"maps for {name}")
        builds[name] = _in_process(_prepare_maps, name, data, config)
    rows = []
    if config.baseline and "orb" in config.features:
        if progress:
            progress("the plain ORB tile loop (baseline)")
        rows.append({"features": "orb", "engine": "opencv", "fix_source": BASELINE})
        rows[-1] |= _in_process(_measure_baseline, data, config)
    for name, engine, fix_source, backbone in config.measured():
        run = {"features": name, "engine": engine, "fix_source": fix_source}
        if backbone is not None:
            run["coarse_backbone"] = backbone
        if progress:
            progress(" ".join([f"{name} on {engine}, {fix_source}", backbone or ""]).strip())
        rows.append(run | _in_process(_measure, run, data, config))
    result = {
        "config": asdict(config),
        "data": {
            "naip_map": str(data.naip_map),
            "naip_frames": str(data.naip_frames),
            "real": str(data.real) if data.real else None,
        },
        "cpu_cores": os.cpu_count(),
        "map_build_s": builds,
        "rows": rows,
        "machine": watch.record(),
    }
    write_json_atomic(out, result)
    plot_speed_bench(rows, out.with_suffix(".png"))
    return result


def table_rows(result: dict) -> list[dict]:
    """One flat row per run for the printed table (false fixes: their share of all NAIP frames)."""
    out = []
    for row in result["rows"]:
        cross, same, real = row["naip"]["cross-date"], row["naip"]["same-date"], row.get("real") or {}
        latency = row.get("latency") or {}
        out.append(
            {
                "features": row["features"],
                "engine": row["engine"],
                "fix_source": row.get("fix_source", KEYPOINTS),
                "coarse_backbone": row.get("coarse_backbone", ""),
                "naip_same_ms": same["total_ms"],
                "naip_cross_ms": cross["total_ms"],
                "same_within_10m": same["centre_within_10m"],
                "cross_within_10m": cross["centre_within_10m"],
                "cross_within_25m": cross["within_25m"],
                "false_fixes": round((same["false_fix_rate"] + cross["false_fix_rate"]) / 2.0, 3),
                "real_ms": real.get("total_ms"),
                "real_fps": real.get("fps"),
                "real_fixed": real.get("fixed"),
                "real_within_3m": real.get("within_3m"),
                "real_false": real.get("false_fixes"),
                "peak_rss_mb": row["peak_rss_mb"],
                "latency_p95_ms": latency.get("latency_p95_ms"),
                "dropped": latency.get("frames_dropped"),
            }
        )
    return out


def tail_rows(result: dict) -> list[dict]:
    """One row per run, condition and stage: the stage's p50 / p95 / p99 / max over the frames."""
    out = []
    for row in result["rows"]:
        label = " ".join(
            filter(None, (row["features"], row["engine"], row["fix_source"], row.get("coarse_backbone")))
        )
        parts = {f"NAIP {k}": v for k, v in row["naip"].items()} | {"photos": row.get("real") or {}}
        for condition, part in parts.items():
            for stage, tails in part.get("tails_ms", {}).items():
                out.append({"run": label, "frames": condition, "stage": stage, **tails})
    return out


# --- data -------------------------------------------------------------------------------------


def _naip_pair(naip_dir: Path, config: SpeedBenchConfig) -> tuple[Path, Path]:
    tifs = sorted(naip_dir.glob("*.tif"))

    def one(year: str, role: str) -> Path:
        found = [p for p in tifs if year in p.stem]
        if len(found) != 1:
            raise OrthonavError(
                f"{naip_dir}: expected one GeoTIFF whose name holds {year!r} ({role}), found {len(found)}"
            )
        return found[0]

    return one(config.map_year, "the map"), one(config.frames_year, "the cross-date frames")


def _real(real_dir: Path | None) -> Path | None:
    if real_dir is None:
        return None
    missing = [n for n in ("ortho.tif", "camera.json", "queries.csv") if not (real_dir / n).is_file()]
    if missing:
        raise OrthonavError(f"{real_dir}: not a real-photo dataset ({', '.join(missing)} missing)")
    return real_dir


def _spread(items: list, count: int) -> list:
    """``count`` items evenly spread over the list (all of them when it is shorter)."""
    if count >= len(items):
        return items
    return [items[int(i)] for i in np.linspace(0, len(items) - 1, count).round()]


# --- the runs, each in a process of its own ---------------------------------------------------


def _in_process(fn: Callable, *args: object) -> dict:
    """``fn(*args)`` in a fresh process (spawned: no thread pool or allocation carried over)."""
    with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
        return pool.submit(fn, *args).result()


def _naip_setup(name: str, data: _Data, config: SpeedBenchConfig) -> tuple[LocalizeBenchConfig, Camera, Path]:
    naip = LocalizeBenchConfig(frames=config.frames, seed=config.seed, features=(name,), speed_sizes=())
    return naip, Camera.from_hfov(naip.width, naip.height, naip.hfov_deg), data.maps / "naip"


def _naip_map(name: str, data: _Data, config: SpeedBenchConfig) -> MapPackage:
    naip, camera, where = _naip_setup(name, data, config)
    return build_bench_map(data.naip_map, naip.alt_m, where, camera, name, {}, None)


def _real_map(name: str, data: _Data, config: SpeedBenchConfig) -> MapPackage:
    camera = Camera.from_json(data.real / "camera.json")
    queries = read_queries(data.real)
    dsm = data.real / "dsm.tif"
    return dataset_map(data.real, data.maps / "real", camera, name, queries, dsm, config.max_frame_px)


def _prepare_maps(name: str, data: _Data, config: SpeedBenchConfig) -> dict:
    """Build (or find) the backend's maps; seconds spent on each (0 when found)."""
    times = {}
    for label, build in (
        ("naip", lambda: _naip_map(name, data, config)),
        ("real", lambda: _real_map(name, data, config)),
    ):
        if label == "real" and data.real is None:
            continue
        t0 = time.perf_counter()
        build()
        times[label] = round(time.perf_counter() - t0, 1)
    return times


def _measure(run: dict, data: _Data, config: SpeedBenchConfig) -> dict:
    """One backend on one engine as one fix source (``run``: its row's keys): NAIP same- and
    cross-date, real photos, optionally the loop."""
    name, fix_source = run["features"], run["fix_source"]
    backbone = run.get("coarse_backbone", DEFAULT_COARSE_BACKBONE)
    runtime = _runtime(run["engine"])
    naip, camera, _ = _naip_setup(name, data, config)
    package = _naip_map(name, data, config)
    result: dict = {"naip": {}}
    with GeoRaster(data.naip_map) as raster:
        backend = package.create_backend(runtime)
        source = make_fix_source(fix_source, package, camera, raster, None, backend, backbone)
        warm_up(source, raster, camera, naip.alt_m)
        for condition, samples in _naip_conditions(data, camera, naip):
            recorded = _Recorded(source)
            row = evaluate_samples(recorded, package.gsd_m, samples, "prior")
            result["naip"][condition] = _keep(row, NAIP_ACCURACY) | {"tails_ms": tails(recorded.timings)}
        if config.latency_s:
            result["latency"] = _latency(package, camera, run, raster, data, config, backend)
    if data.real is not None and config.photos:
        result["real"] = _real_photos(name, fix_source, backbone, data, config, runtime)
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    return result


def _naip_conditions(data: _Data, camera: Camera, naip: LocalizeBenchConfig) -> list[tuple[str, list]]:
    """The NAIP frames of each condition, rendered alike for every run (seeded per file)."""
    band = (naip.alt_m, naip.alt_m)
    frames = (("same-date", data.naip_map), ("cross-date", data.naip_frames))
    return [(condition, render_samples(path, camera, band, naip)) for condition, path in frames]


class _Recorded:
    """A fix source that keeps each frame's stage times, for their tails."""

    def __init__(self, source: object) -> None:
        self.source = source
        self.timings: list[dict[str, float]] = []

    def localize(self, frame: np.ndarray, prior: Prior) -> Fix:
        fix = self.source.localize(frame, prior)
        self.timings.append(dict(fix.timings_ms))
        return fix


def tails(timings: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Each stage's p50 / p95 / p99 / max over the frames that reached it, and the total's."""
    return stage_tails(timings, (*STAGES, "total_ms"))


def _measure_baseline(data: _Data, config: SpeedBenchConfig) -> dict:
    """The plain tile loop on ORB's NAIP map and frames; its accuracy is its frame centre's."""
    naip, camera, _ = _naip_setup("orb", data, config)
    loop = PlainTileLoop(_naip_map("orb", data, config))
    result: dict = {"naip": {}}
    for condition, samples in _naip_conditions(data, camera, naip):
        loop.locate(samples[0].frame, samples[0].prior)  # tiles read and caches warm, as warm_up does
        fixes = [loop.locate(s.frame, s.prior) for s in samples]
        result["naip"][condition] = _plain_row(fixes, [s.centre for s in samples])
    result["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    return result


def _plain_row(fixes: list[PlainFix], centres: list[tuple[float, float]]) -> dict:
    """The loop's row as orthonav's rows have it: shares of all frames, stage medians, means, tails."""
    errors = np.array(
        [
            error_m(*truth, *fix.centre) if fix.centre else np.inf
            for fix, truth in zip(fixes, centres, strict=True)
        ]
    )
    n, fixed = len(errors), errors[np.isfinite(errors)]
    timings = [fix.timings_ms for fix in fixes]
    medians = {k: median(t[k] for t in timings) for k in timings[0]}
    means = {k: mean(t[k] for t in timings) for k in timings[0] if k != "total_ms"}
    total = mean(t["total_ms"] for t in timings)
    means |= {"other_ms": round(max(0.0, total - sum(means.values())), 1), "total_ms": total}
    return {
        "fix_rate": share(np.isfinite(errors), n),
        **within_rates(fixed, n, (10, 25)),
        **within_rates(fixed, n, (10, 25), prefix="centre_within_"),
        "false_fix_rate": wrong_rate(fixed, n, FALSE_FIX_M),
        **medians,
        "mean_ms": means,
        "tails_ms": tails(timings),
    }


def _runtime(engine: str) -> Runtime:
    """Where a run's learned backend computes: OpenCV's and the torch/ONNX engines on the CPU
    (the correlation's trunk follows $ORTHONAV_RUNTIME, set in this run's process only; it stays
    fp32 under ``onnx-int8``), ``cuda`` torch on the GPU."""
    if engine == "opencv":
        return Runtime()
    if engine == "cuda":
        os.environ["ORTHONAV_RUNTIME"] = "torch"
        return Runtime("cuda", engine="torch")
    name, _, precision = engine.partition("-")
    os.environ["ORTHONAV_RUNTIME"] = name
    return Runtime(engine=name, precision=precision or "fp32")


def _real_photos(
    name: str, fix_source: str, backbone: str, data: _Data, config: SpeedBenchConfig, runtime: Runtime
) -> dict:
    """The spread photos on the DSM with the EXIF prior; decoding timed with the rest."""
    package = _real_map(name, data, config)
    camera = Camera.from_json(data.real / "camera.json")
    prior_config = RealBenchConfig(features=(name,), variants=("dsm",), seed=config.seed)
    rng = np.random.default_rng(config.seed)
    outcomes: list = []
    with ExitStack() as stack:
        raster = stack.enter_context(GeoRaster(data.real / "ortho.tif"))
        localizer = LocalizerConfig(use_terrain=True)
        backend = package.create_backend(runtime)
        source = make_fix_source(fix_source, package, camera, raster, localizer, backend, backbone)
        warm_up(source, raster, camera, package.tiling.nominal_alt_m)  # timed as fly runs it
        for query in _spread(read_queries(data.real), config.photos):
            t0 = time.perf_counter()
            frame = load_frame(query.path)
            decode_ms = (time.perf_counter() - t0) * 1000.0
            outcome = score(query, source.localize(frame, make_prior(query, prior_config, False, rng)))
            outcome.timings_ms["decode_ms"] = decode_ms
            outcome.timings_ms["total_ms"] += decode_ms
            outcomes.append(outcome)
    row = metrics(outcomes)
    kept = _keep(row, ("fixed", "within_3m", "false_fixes", "within_3sigma"))
    fps = round(1000.0 / kept["total_ms"], 2) if kept["total_ms"] else None
    return kept | {"fps": fps, "tails_ms": tails([o.timings_ms for o in outcomes])}


def _latency(
    package: MapPackage,
    camera: Camera,
    run: dict,
    raster: GeoRaster,
    data: _Data,
    config: SpeedBenchConfig,
    backend: FeatureBackend,
) -> dict:
    """The companion loop with ``run``'s fix source over the map's orthophoto ``raster``, its
    frames rendered from ``config.latency_frames``' orthophoto."""
    from orthonav.bench.mission import MissionBenchConfig, companion_latency
    from orthonav.sim import SIMULATED_WORLD

    name, fix_source = run["features"], run["fix_source"]
    backbone = run.get("coarse_backbone", DEFAULT_COARSE_BACKBONE)
    mission = MissionBenchConfig(missions=1, features=(name,), latency_s=config.latency_s, seed=config.seed)
    source = make_fix_source(fix_source, package, camera, raster, SIMULATED_WORLD, backend, backbone)
    label = "_".join([name, fix_source, backbone.replace(">", "-")])
    with ExitStack() as stack:
        cross = config.latency_frames == "cross-date"
        frames_from = stack.enter_context(GeoRaster(data.naip_frames)) if cross else raster
        return companion_latency(package, source, raster, camera, label, mission, frames_from)


def _keep(row: dict, accuracy: tuple[str, ...]) -> dict:
    """The accuracy keys, every stage's median ms and the median total; ``mean_ms``: every
    stage's mean per frame and the rest of the mean total as ``other_ms`` (medians of stages
    that only some frames reach do not add up to the median total; means do)."""
    timed = {**row.get("stage_ms", {}), **{k: row[k] for k in STAGES if row.get(k) is not None}}
    stages = {k: timed[k] for k in STAGES if timed.get(k) is not None}
    mean_stage = row.get("mean_stage_ms", {})
    means = {k: v for k, v in mean_stage.items() if k in STAGES}
    total = mean_stage.get("total_ms")
    other = None if total is None else round(max(0.0, total - sum(means.values())), 1)
    mean_ms = means | {"other_ms": other, "total_ms": total}
    return {k: row[k] for k in accuracy} | stages | {"total_ms": row.get("total_ms"), "mean_ms": mean_ms}
