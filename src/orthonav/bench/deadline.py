"""Per-frame time of the cascade with and without a frame budget, on the same frames, and of
LightGlue's engines on the same pairs: what ``fly --frame-budget-ms`` buys on a loaded CPU.

``python -m orthonav.bench.deadline DATA_DIR --out docs/benchmarks/results/bench_deadline.json``
(DATA_DIR holds naip/; ``--busy-core`` keeps a second process busy on one core meanwhile, the
loaded case; ``--busy-cores N``, N such processes). Each frame is localized unbounded and then
with the budget, in turn, so both see the same load; the rows give per-frame p50 / p95 / p99 /
max, the frames over the budget by more than a tenth, the fixes and the wrong ones, each stage's
(the keypoint stage's steps as ``fine_extract_ms`` and so on) and the slowest frame's stage times
(which stage overran).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from orthonav.bench.localize import LocalizeBenchConfig, Sample, render_samples
from orthonav.bench.machine import LoadWatch
from orthonav.camera import Camera
from orthonav.features import FeatureBackend, FeatureSet, Runtime, create_backend
from orthonav.frames import render_frame
from orthonav.geo import GeoRaster, distance_m
from orthonav.localize import make_fix_source, warm_up
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.types import Fix

ALT_M = 1000.0
MAP_YEAR, FRAMES_YEAR = "20200831", "20180716"
WRONG_M = 50.0
OVER_SHARE = 0.1  # a frame over its budget by more than this share of it is late


def naip(data_dir: Path, year: str) -> Path:
    return data_dir / "naip" / f"m_4709963_se_14_1_{year}.tif"


def quantiles_ms(times: list[float]) -> dict[str, float]:
    """p50, p95, p99 and max of ``times`` (ms), rounded to the millisecond."""
    p50, p95, p99 = np.percentile(times, [50, 95, 99])
    return {
        "p50_ms": round(float(p50)),
        "p95_ms": round(float(p95)),
        "p99_ms": round(float(p99)),
        "max_ms": round(max(times)),
    }


def _row(
    name: str, samples: list[Sample], fixes: list[Fix], times: list[float], budget_ms: float | None
) -> dict:
    errors = [
        float(distance_m(s.truth.lat, s.truth.lon, f.pose.lat, f.pose.lon))
        for s, f in zip(samples, fixes, strict=True)
        if f.accepted
    ]
    return {
        "run": name,
        "frames": len(fixes),
        **quantiles_ms(times),
        "fixed": len(errors),
        "within_10m": sum(e <= 10.0 for e in errors),
        "wrong_over_50m": sum(e > WRONG_M for e in errors),
        "deadline": sum("deadline" in f.reason or "deadline_cut" in f.quality for f in fixes),
        "fine_max_ms": round(max(f.timings_ms.get("fine_ms", 0.0) for f in fixes)),
        "coarse_max_ms": round(max(f.timings_ms.get("coarse_ms", 0.0) for f in fixes)),
        "late": None if budget_ms is None else sum(t > (1.0 + OVER_SHARE) * budget_ms for t in times),
        "slowest_frame_ms": {key: round(ms) for key, ms in fixes[int(np.argmax(times))].timings_ms.items()},
        "stages": stage_quantiles(fixes),
        "per_frame": [_frame_record(f, ms) for f, ms in zip(fixes, times, strict=True)],
    }


def stage_quantiles(fixes: list[Fix]) -> dict[str, dict[str, float]]:
    """Each stage's p50 / p95 / p99 / max over the frames it ran on, and on how many: where the
    tail of the frame's time comes from."""
    stages = dict.fromkeys(key for f in fixes for key in f.timings_ms)
    out = {}
    for stage in stages:
        times = [f.timings_ms[stage] for f in fixes if stage in f.timings_ms]
        out[stage] = {"frames": len(times), **quantiles_ms(times)}
    return out


def _frame_record(fix: Fix, ms: float) -> dict:
    """One frame's time, its stages' and its outcome (the reason's first clause)."""
    return {
        "ms": round(ms),
        "accepted": fix.accepted,
        "reason": fix.reason.split(";")[0][:120],
        "stages_ms": {key: round(value) for key, value in fix.timings_ms.items()},
    }


def cascade_rows(
    package: MapPackage, raster: GeoRaster, camera: Camera, samples: list[Sample], budget_ms: float
) -> list[dict]:
    """The default cascade chain (as ``fly`` runs it) unbounded and with ``budget_ms``, frame by
    frame in turn, both warmed up first."""
    backend = package.create_backend()
    budgets = {"unbounded": None, f"budget {budget_ms:g} ms": budget_ms}
    sources = {
        name: make_fix_source("cascade", package, camera, raster, backend=backend, frame_budget_ms=budget)
        for name, budget in budgets.items()
    }
    for source in sources.values():
        warm_up(source, raster, camera, ALT_M)
    fixes: dict[str, list[Fix]] = {name: [] for name in sources}
    times: dict[str, list[float]] = {name: [] for name in sources}
    for sample in samples:
        for name, source in sources.items():
            start = time.perf_counter()
            fixes[name].append(source.localize(sample.frame, sample.prior))
            times[name].append((time.perf_counter() - start) * 1000.0)
    return [_row(name, samples, fixes[name], times[name], budgets[name]) for name in sources]


def glue_rows(backend: FeatureBackend, pairs: list[tuple[FeatureSet, FeatureSet]]) -> list[dict]:
    """LightGlue's time per pair under torch as torch threads by default, on one thread (what a
    CPU runtime without a thread count now gets) and under ONNX Runtime (its cached graphs)."""
    import torch

    from orthonav.features.lightglue import backend_lightglue

    one = backend_lightglue(backend)
    matchers = {"torch, default threads": one.glue, "torch, one thread": one}
    onnx = backend._cached_onnx_matcher() if hasattr(backend, "_cached_onnx_matcher") else None
    if onnx is not None:
        matchers["ONNX Runtime"] = onnx
    rows = []
    for name, glue in matchers.items():
        glue(pairs[0][0], [pairs[0][1]])  # loaded and warmed
        times = []
        for query, train in pairs:
            start = time.perf_counter()
            glue(query, [train])
            times.append((time.perf_counter() - start) * 1000.0)
        threads = torch.get_num_threads()
        rows.append({"matcher": name, "pairs": len(pairs), "torch_threads": threads, **quantiles_ms(times)})
    return rows


def glue_pairs(backend: FeatureBackend, data_dir: Path, camera: Camera, samples: list[Sample]) -> list:
    """Each frame's keypoints and those of the map year's picture at its pose: a cross-date pair."""
    pairs = []
    with GeoRaster(naip(data_dir, MAP_YEAR)) as raster:
        for sample in samples:
            other = render_frame(raster, camera, sample.truth)
            grays = [cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) for image in (sample.frame, other)]
            pairs.append(tuple(backend.extract(gray) for gray in grays))
    return pairs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data_dir", type=Path)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--work", type=Path, default=Path("runs/bench_deadline"))
    parser.add_argument("--features", default="aliked")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--glue-pairs", type=int, default=6)
    parser.add_argument("--budget-ms", type=float, default=500.0)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--busy-core", action="store_true", help="a second process spins meanwhile")
    parser.add_argument("--busy-cores", type=int, default=0, help="this many processes spin meanwhile")
    args = parser.parse_args()
    args.busy_cores = max(args.busy_cores, int(args.busy_core))
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy_cores)]
    try:
        result = run(args)
    finally:
        for process in busy:
            process.kill()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    rows = [{k: v for k, v in row.items() if k != "per_frame"} for row in result["rows"]]
    print(json.dumps({"rows": rows, "lightglue": result["lightglue"]}, indent=2))


def run(args: argparse.Namespace) -> dict:
    """The result file's content: the cascade's rows, LightGlue's, the machine."""
    watch = LoadWatch()
    camera = Camera.from_hfov(640, 480, 60.0)  # the NAIP benchmarks' camera
    map_dir = args.work / f"map_{args.features}"
    if map_dir.is_dir():
        package = MapPackage(map_dir)
    else:
        tiling = TilingConfig(nominal_alt_m=ALT_M)
        ortho = naip(args.data_dir, MAP_YEAR)
        package = build_map(ortho, map_dir, camera, tiling, args.features, progress=False)
    config = LocalizeBenchConfig(frames=args.frames, seed=args.seed)
    samples = render_samples(naip(args.data_dir, FRAMES_YEAR), camera, (ALT_M, ALT_M), config)
    with GeoRaster(naip(args.data_dir, MAP_YEAR)) as raster:
        rows = cascade_rows(package, raster, camera, samples, args.budget_ms)
    backend = create_backend(args.features, Runtime())
    glue = []
    if args.glue_pairs > 0:
        glue = glue_rows(backend, glue_pairs(backend, args.data_dir, camera, samples[: args.glue_pairs]))
    return {
        "benchmark": "deadline",
        "busy_core": args.busy_cores > 0,
        "busy_processes": args.busy_cores,
        "map_year": MAP_YEAR,
        "frames_year": FRAMES_YEAR,
        "features": args.features,
        "engine": backend.engine,
        "budget_ms": args.budget_ms,
        "seed": args.seed,
        "rows": rows,
        "lightglue": glue,
        "machine": watch.record(),
    }


if __name__ == "__main__":
    main()
