"""``orthonav bench runtime``: the learned correction, the retrieval network and XFeat's keypoints
under torch, ONNX Runtime fp32 and ONNX Runtime int8, side by side on the same frames.

Per runtime and correction size: the median time of a whole correction (views, CNN features of
the region and of the frame at each turn, correlation, refinement) over every frame after a
warm-up, and of the trunk alone on the region view (the runtimes take turns on each frame, so
a change of the machine's load falls on all alike); the accepted fixes' errors against the
truth and their distance to torch's fix of the same frame. Per runtime: the median time of one
index descriptor (a map tile) and the descriptors' cosine to torch's. XFeat (``xfeat-mnn``'s
extraction, torch vs ONNX Runtime fp32; its int8 export is refused as it moves keypoints) at each of
``xfeat_threads``: the median time per 640 x 480 frame and how ONNX's features agree with torch's
(keypoints at the same pixel, descriptor cosine, score ratio).

Frames of one NAIP date are rendered at known poses over the map of another; int8's activation
ranges are calibrated on a third date. Torch and ONNX Runtime get the same threads (one per
physical core unless told). The machine's load is recorded: other jobs slow every runtime.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.bench.scoring import error_m
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureSet
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, destination, distance_m
from orthonav.localize import CorrectionConfig, Corrector
from orthonav.models import SHIPPED_RETRIEVAL_MODEL, shipped_model_path
from orthonav.models.onnx.loading import load_onnx_retrieval
from orthonav.models.onnx.runtime import physical_cores
from orthonav.types import Fix, Prior

RUNTIMES = ("torch", "onnx-fp32", "onnx-int8")
PARTS = ("corrections", "index", "xfeat")
XFEAT_RUNTIMES = ("torch", "onnx-fp32")


@dataclass(frozen=True)
class RuntimeBenchConfig:
    """Everything that decides the numbers; written beside them."""

    map_date: str = "20180716"
    frames_date: str = "20200831"
    calibration_date: str = "20120731"
    frames: int = 8
    sizes: tuple[int, ...] = (224, 448)
    repeats: int = 5
    tiles: int = 8
    tile_px: int = 346
    calibration_crops: int = 32
    runtimes: tuple[str, ...] = RUNTIMES
    threads: int | None = None  # default: one per physical core
    seed: int = 0
    model_path: str | None = None
    retrieval_model_path: str | None = None
    parts: tuple[str, ...] = PARTS
    xfeat_threads: tuple[int, ...] = (1, 2)

    def __post_init__(self) -> None:
        if self.frames < 1 or self.repeats < 1 or self.tiles < 1 or not self.sizes:
            raise OrthonavError("bench runtime: expected frames, repeats, tiles >= 1 and at least one size")
        unknown = set(self.runtimes) - set(RUNTIMES)
        if unknown or "torch" not in self.runtimes:
            raise OrthonavError(f"bench runtime: runtimes among {', '.join(RUNTIMES)}, torch included")
        if not self.parts or set(self.parts) - set(PARTS):
            raise OrthonavError(f"bench runtime: parts among {', '.join(PARTS)}, got {self.parts}")
        if not self.xfeat_threads or min(self.xfeat_threads) < 1:
            raise OrthonavError(
                f"bench runtime: xfeat_threads must be positive counts, got {self.xfeat_threads}"
            )

    @property
    def camera(self) -> Camera:
        return Camera.from_hfov(640, 480, 60.0)


@dataclass
class _Case:
    truth: TruePose
    frame: np.ndarray
    prior: Prior


def run_runtime_benchmark(
    naip_dir: Path, out_json: Path, config: RuntimeBenchConfig = RuntimeBenchConfig(), progress: bool = True
) -> dict:
    """Export (into ``onnx/`` beside ``out_json``; XFeat's into the cache, as at first use), time and
    compare ``config.parts``; return and write the results."""
    import torch

    from orthonav.models.train import dates_in

    map_path, frames_path, calibration_path = dates_in(
        naip_dir, [config.map_date, config.frames_date, config.calibration_date]
    )
    threads = config.threads or physical_cores()
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    watch = LoadWatch()
    rows = {}
    try:
        trunks = {"corrections", "index"} & set(config.parts)
        files = _exports(config, out_json.parent / "onnx", calibration_path) if trunks else {}
        with GeoRaster(map_path) as raster, GeoRaster(frames_path) as frames_raster:
            cases = list(_cases(raster, frames_raster, config))
            if "corrections" in config.parts:
                rows["corrections"] = _correction_rows(raster, cases, files, config, threads, progress)
            if "index" in config.parts:
                rows["index"] = _index_rows(raster, files, config, threads)
            if "xfeat" in config.parts:
                rows["xfeat"] = _xfeat_rows(cases, config)
    finally:
        torch.set_num_threads(before)
    result = {
        "config": {**asdict(config), "time": time.strftime("%Y-%m-%d %H:%M:%S")},
        "machine": _machine(threads, watch),
        "data": {"map": map_path.name, "frames": frames_path.name, "calibration": calibration_path.name},
        **rows,
    }
    write_json_atomic(out_json, result)
    _plot(result, out_json.with_suffix(".png"))
    return result


def _exports(config: RuntimeBenchConfig, cache: Path, calibration_path: Path) -> dict[tuple[str, str], Path]:
    """(model kind, runtime) -> ONNX file, exported here (an up-to-date file is kept)."""
    from orthonav.models.export import calibration_crops, export_onnx

    models = {"correction": _correction_model(config), "retrieval": _retrieval_model(config)}
    crops = calibration_crops([calibration_path], config.calibration_crops, seed=config.seed)
    files = {}
    for kind, model in models.items():
        for runtime in config.runtimes:
            if runtime.startswith("onnx-"):
                precision = runtime.removeprefix("onnx-")
                files[kind, runtime] = export_onnx(model, precision, cache_dir=cache, calibration=crops)
    return files


def _correction_model(config: RuntimeBenchConfig) -> Path:
    return Path(config.model_path) if config.model_path else shipped_model_path()


def _retrieval_model(config: RuntimeBenchConfig) -> Path:
    path = config.retrieval_model_path
    return Path(path) if path else shipped_model_path(SHIPPED_RETRIEVAL_MODEL)


# --- corrections ------------------------------------------------------------------------------


def _cases(raster: GeoRaster, frames: GeoRaster, config: RuntimeBenchConfig) -> Iterator[_Case]:
    """Frames of another date at random poses, priors 10-15 m off with heading/altitude errors."""
    rng = np.random.default_rng(config.seed)
    for _ in range(config.frames):
        col = rng.uniform(0.2, 0.8) * raster.width
        row = rng.uniform(0.25, 0.75) * raster.height
        lat, lon = raster.pixel_to_latlon(col, row)
        alt = rng.uniform(500.0, 700.0)
        truth = TruePose(float(lat), float(lon), alt, rng.uniform(0, 360), *rng.uniform(-3, 3, 2))
        frame = render_frame(frames, config.camera, truth, Photometric.random(rng, 0.5), rng)
        lat, lon = destination(truth.lat, truth.lon, rng.uniform(0, 360), rng.uniform(10.0, 15.0))
        heading = (truth.yaw_deg + rng.normal(0.0, 1.5)) % 360.0
        prior = Prior(
            lat,
            lon,
            alt * rng.uniform(0.97, 1.03),
            heading,
            truth.pitch_deg,
            truth.roll_deg,
            heading_sigma_deg=2.0,
        )
        yield _Case(truth, frame, prior)


def _correction_rows(
    raster: GeoRaster,
    cases: list[_Case],
    files: dict[tuple[str, str], Path],
    config: RuntimeBenchConfig,
    threads: int,
    progress: bool,
) -> list[dict]:
    rows = []
    for size in config.sizes:
        correctors = {
            runtime: Corrector(
                raster, config.camera, _correction_config(config, runtime, size, files, threads)
            )
            for runtime in config.runtimes
        }
        fixes, times = _time_corrections(correctors, cases, config.repeats, progress)
        trunk = _trunk_ms(correctors, cases[0], config.repeats)
        for runtime in config.runtimes:
            timing = {
                "median_ms": _r(1000.0 * float(np.median(times[runtime]))),
                "trunk_ms": _r(trunk[runtime]),
            }
            rows.append(
                {"runtime": runtime, "size": size, **timing}
                | _accuracy(fixes[runtime], fixes["torch"], cases)
            )
    return rows


def _correction_config(
    config: RuntimeBenchConfig, runtime: str, size: int, files: dict, threads: int
) -> CorrectionConfig:
    common = {"backbone": "trained", "size_px": size, "model_path": str(_correction_model(config))}
    if runtime == "torch":
        return CorrectionConfig(**common, runtime="torch")
    precision = runtime.removeprefix("onnx-")
    onnx = {
        "onnx_precision": precision,
        "onnx_path": str(files["correction", runtime]),
        "onnx_threads": threads,
    }
    return CorrectionConfig(**common, runtime="onnx", **onnx)


def _time_corrections(
    correctors: dict[str, Corrector], cases: list[_Case], repeats: int, progress: bool
) -> tuple[dict[str, list[Fix]], dict[str, list[float]]]:
    """Each runtime's fix of every frame and its times (s). The runtimes take turns on every
    frame, so a change in the machine's load (other jobs) falls on all of them alike."""
    for corrector in correctors.values():  # warm-up
        corrector.correct(cases[0].frame, cases[0].prior)
    fixes: dict[str, list[Fix]] = {name: [] for name in correctors}
    times: dict[str, list[float]] = {name: [] for name in correctors}
    for case in tqdm(cases, desc="corrections", disable=not progress):
        for k in range(repeats):
            for name, corrector in correctors.items():
                t0 = time.perf_counter()
                fix = corrector.correct(case.frame, case.prior).fix
                times[name].append(time.perf_counter() - t0)
                if k == 0:
                    fixes[name].append(fix)
    return fixes, times


def _trunk_ms(correctors: dict[str, Corrector], case: _Case, repeats: int) -> dict[str, float]:
    """Median ms of each runtime's trunk on one region view (the largest input of a correction)."""
    views = next(iter(correctors.values())).correct(case.frame, case.prior).views
    runs = {
        name: lambda c=corrector: c.network.image_features(views.region, views.region_mask)
        for name, corrector in correctors.items()
    }
    return _interleaved_ms(runs, repeats)


def _accuracy(fixes: list[Fix], reference: list[Fix], cases: list[_Case]) -> dict:
    """Errors of the accepted fixes against the truth, and the largest distance to torch's fixes."""
    errors = [
        error_m(c.truth.lat, c.truth.lon, f.pose.lat, f.pose.lon)
        for f, c in zip(fixes, cases, strict=True)
        if f.accepted
    ]
    apart = [
        float(distance_m(f.pose.lat, f.pose.lon, r.pose.lat, r.pose.lon))
        for f, r in zip(fixes, reference, strict=True)
        if f.accepted and r.accepted
    ]
    same = sum(f.accepted == r.accepted for f, r in zip(fixes, reference, strict=True))
    return {
        "accepted": f"{len(errors)}/{len(fixes)}",
        "median_error_m": _r(float(np.median(errors))) if errors else None,
        "max_error_m": _r(max(errors)) if errors else None,
        "same_decision": f"{same}/{len(fixes)}",
        "max_vs_torch_m": _r(max(apart), 3) if apart else None,
    }


# --- index descriptors ------------------------------------------------------------------------


def _index_rows(
    raster: GeoRaster, files: dict[tuple[str, str], Path], config: RuntimeBenchConfig, threads: int
) -> list[dict]:
    from orthonav.models.retrieval import load_retrieval_model

    tiles = _tiles(raster, config)
    model = _retrieval_model(config)
    networks = {}
    for runtime in config.runtimes:
        if runtime == "torch":
            networks[runtime] = load_retrieval_model(model)[0]
        else:
            precision = runtime.removeprefix("onnx-")
            networks[runtime] = load_onnx_retrieval(
                model, precision, files["retrieval", runtime], threads=threads
            )
    vectors = {
        name: np.stack([n.describe(gray, mask) for gray, mask in tiles]) for name, n in networks.items()
    }
    runs = {
        name: lambda n=network: [n.describe(g, m) for g, m in tiles] for name, network in networks.items()
    }
    times = _interleaved_ms(runs, config.repeats)
    rows = []
    for runtime in config.runtimes:
        cosines = (vectors[runtime] * vectors["torch"]).sum(axis=1)
        rows.append(
            {
                "runtime": runtime,
                "tile_px": config.tile_px,
                "median_ms": _r(times[runtime] / len(tiles)),
                "min_cosine_to_torch": round(float(cosines.min()), 5),
                "mean_cosine_to_torch": round(float(cosines.mean()), 5),
            }
        )
    return rows


def _tiles(raster: GeoRaster, config: RuntimeBenchConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """Tile-sized gray crops of the map (the last with a partial mask, as at a map's edge)."""
    rng = np.random.default_rng(config.seed + 1)
    image = cv2.cvtColor(raster.read_rgb(), cv2.COLOR_RGB2GRAY)
    side = min(config.tile_px, *image.shape)
    tiles = []
    for k in range(config.tiles):
        y = int(rng.integers(0, image.shape[0] - side + 1))
        x = int(rng.integers(0, image.shape[1] - side + 1))
        mask = np.ones((side, side), np.uint8)
        if k == config.tiles - 1:
            mask[:, : side // 3] = 0
        tiles.append((np.ascontiguousarray(image[y : y + side, x : x + side]) * mask, mask))
    return tiles


# --- XFeat -------------------------------------------------------------------------------------


def _xfeat_rows(cases: list[_Case], config: RuntimeBenchConfig) -> list[dict]:
    """Per thread count and runtime: XFeat's extraction of the frames (640 x 480), the runtimes
    taking turns; the agreement of ONNX Runtime's features with torch's at the same threads."""
    from orthonav.features import Runtime, create_backend

    frames = [cv2.cvtColor(case.frame, cv2.COLOR_BGR2GRAY) for case in cases]
    height, width = frames[0].shape
    rows = []
    for threads in config.xfeat_threads:
        # torch's thread count is set when its backend is made: the torch one comes last
        backends = {
            runtime: create_backend("xfeat-mnn", Runtime(threads=threads, engine=runtime.split("-")[0]))
            for runtime in reversed(XFEAT_RUNTIMES)
        }
        features = {name: [b.extract(gray) for gray in frames] for name, b in backends.items()}
        runs = {name: lambda b=b: [b.extract(gray) for gray in frames] for name, b in backends.items()}
        times = _interleaved_ms(runs, config.repeats)
        for runtime in XFEAT_RUNTIMES:
            agreement = [
                feature_agreement(want, got)
                for want, got in zip(features["torch"], features[runtime], strict=True)
            ]
            rows.append(
                {
                    "runtime": runtime,
                    "threads": threads,
                    "size": f"{width}x{height}",
                    "median_ms": _r(times[runtime] / len(frames)),
                    "speedup_vs_torch": round(times["torch"] / times[runtime], 2),
                    "keypoints": round(float(np.mean([len(f) for f in features[runtime]]))),
                    "kept_vs_torch": min(a["kept"] for a in agreement),
                    "min_cosine_to_torch": min(a["min_cosine"] for a in agreement),
                    "max_score_ratio": max(a["max_score_ratio"] for a in agreement),
                }
            )
    return rows


def feature_agreement(reference: FeatureSet, other: FeatureSet) -> dict[str, float]:
    """How ``other`` reproduces ``reference`` (keypoints on pixels): the fraction of its keypoints
    at the same pixel, and there the smallest descriptor cosine and the largest score ratio - 1."""
    index = {(int(x), int(y)): i for i, (x, y) in enumerate(other.keypoints)}
    pairs = [
        (i, index[(int(x), int(y))])
        for i, (x, y) in enumerate(reference.keypoints)
        if (int(x), int(y)) in index
    ]
    if not pairs:
        return {"kept": 0.0, "min_cosine": 0.0, "max_score_ratio": math.inf}
    i, j = np.array(pairs).T
    cosine = (reference.descriptors[i] * other.descriptors[j]).sum(axis=1)
    ratio = np.abs(other.scores[j] / reference.scores[i] - 1.0)
    return {
        "kept": round(len(pairs) / len(reference), 4),
        "min_cosine": round(float(cosine.min()), 7),
        "max_score_ratio": round(float(ratio.max()), 6),
    }


# --- helpers ----------------------------------------------------------------------------------


def _interleaved_ms(runs: dict[str, Callable[[], object]], repeats: int) -> dict[str, float]:
    """Median ms of each run; the runs take turns, after a warm-up of each."""
    for run in runs.values():
        run()
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            t0 = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - t0)
    return {name: 1000.0 * float(np.median(t)) for name, t in times.items()}


def _r(value: float, digits: int = 1) -> float | None:
    return round(value, digits) if math.isfinite(value) else None


def _machine(threads: int, watch: LoadWatch) -> dict:
    """The CPU and how busy it was: other jobs' load slows every runtime alike."""
    return {**watch.record(threads), "physical_cores": physical_cores()}


# part -> (the rows' key the bars are grouped by, y label, x label of a group)
_PANELS = {
    "corrections": ("size", "ms per correction (median)", "{} px"),
    "index": (None, "ms per index descriptor", "tile"),
    "xfeat": ("threads", "ms per XFeat extraction (640x480)", "{} thread(s)"),
}


def _plot(result: dict, out: Path) -> None:
    """One panel per benchmarked part: median ms per group (size, threads), one bar per runtime."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from orthonav.viz.axes import save_figure

    parts = [part for part in PARTS if part in result]
    fig, axes = plt.subplots(1, len(parts), figsize=(1.0 + 3.6 * len(parts), 3.5), squeeze=False)
    for axis, part in zip(axes[0], parts, strict=True):
        _bars(axis, result[part], *_PANELS[part])
    machine = result["machine"]
    threads = f"{machine['threads']} thread{'s' if machine['threads'] != 1 else ''}"
    fig.suptitle(f"{machine['cpu']}, {threads}, load {machine['load_avg_before'][0]}")
    fig.tight_layout()
    save_figure(fig, out)


def _bars(axis: object, rows: list[dict], group_key: str | None, ylabel: str, group_label: str) -> None:
    runtimes = list(dict.fromkeys(r["runtime"] for r in rows))
    groups = list(dict.fromkeys(r.get(group_key) for r in rows)) if group_key else [None]
    width = 0.8 / len(runtimes)
    for k, runtime in enumerate(runtimes):
        ms = [
            next(r["median_ms"] for r in rows if r["runtime"] == runtime and r.get(group_key) == g)
            for g in groups
        ]
        color = f"C{RUNTIMES.index(runtime)}"
        axis.bar(np.arange(len(groups)) + k * width, ms, width, label=runtime, color=color)
    ticks = np.arange(len(groups)) + width * (len(runtimes) - 1) / 2
    axis.set_xticks(ticks, [group_label.format(g) for g in groups])
    axis.set_ylabel(ylabel)
    axis.legend()
