"""``orthonav bench slam``: one camera vs a multi-camera rig vs two UAVs, with and without map fixes.

Per seed, one world (:func:`orthonav.slam.simulate.make_world`): circles over the real NAIP
frames orthophoto, every camera of both UAVs rendered, real visual odometry on the nadir
frames. Every setup runs on that same world: VO alone (no landmarks), one nadir camera, the
nadir + forward + rear rig, two UAVs with a nadir camera each (shared landmarks and the
measured baseline), each without and with map fixes from a real fix source on the map of
another date. Reported per setup: medians over seeds of ATE (UAV 1, the same vehicle in every
setup), RPE, the landmarks' median error and count; and the two-UAV distance/size errors. The
baseline comes from UAV 2 detected in UAV 1's rendered spotter frames: their detection rate,
range error and false detections are reported per flight and, over the map, against range.
"""

from __future__ import annotations

import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.bench.scoring import median
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import create_backend
from orthonav.geo import GeoRaster
from orthonav.localize import orthophoto_fix_source
from orthonav.slam.simulate import (
    SETUPS,
    SlamRun,
    SlamSimConfig,
    default_rig,
    make_world,
    run_setup,
    spotting_summary,
    spotting_sweep,
)
from orthonav.viz.slam import plot_slam_bench

FIX_SOURCES = ("keypoints", "correlation")


@dataclass(frozen=True)
class SlamBenchConfig:
    """Everything that decides the numbers; written beside them."""

    seeds: int = 3
    fix_source: str = "correlation"
    width: int = 640
    height: int = 480
    hfov_deg: float = 60.0
    oblique_deg: float = 25.0
    sweep_ranges_m: tuple[float, ...] = (250.0, 500.0, 1000.0, 2000.0, 3000.0)
    sweep_per_range: int = 12
    sim: SlamSimConfig = field(default_factory=SlamSimConfig)

    def __post_init__(self) -> None:
        if self.fix_source not in FIX_SOURCES:
            raise OrthonavError(
                f"bench slam fix source: expected one of {FIX_SOURCES}, got {self.fix_source!r}"
            )
        if self.seeds < 1:
            raise OrthonavError(f"bench slam seeds: expected at least 1, got {self.seeds}")


def run_slam_benchmark(
    map_tif: Path, frames_tif: Path, out_json: Path, config: SlamBenchConfig, progress: bool = True
) -> dict:
    """Every setup on every seed's world; JSON and a PNG written beside ``out_json``."""
    watch = LoadWatch()
    camera = Camera.from_hfov(config.width, config.height, config.hfov_deg)
    rig = default_rig(camera, config.oblique_deg)
    backend = create_backend(config.sim.features, max_keypoints=config.sim.max_keypoints)
    rows, stereo, spotted, example = [], [], [], {}
    with (
        tempfile.TemporaryDirectory(prefix="orthonav-bench-slam-") as tmp,
        GeoRaster(frames_tif) as frames,
        GeoRaster(map_tif) as map_raster,
    ):
        fix_source = orthophoto_fix_source(config.fix_source, map_raster, camera, Path(tmp), config.sim.alt_m)
        bar = tqdm(total=config.seeds * len(SETUPS), desc="bench slam", disable=not progress)
        for seed in range(config.seeds):
            world = make_world(frames, rig, config.sim, 2, seed)
            spotted.append({"seed": seed, **spotting_summary(world.spotted, config.sim)})
            for setup in SETUPS:
                bar.set_postfix_str(f"seed {seed} {setup.label}")
                run = run_setup(world, setup, fix_source if setup.fixes else None, backend)
                rows.append(_row(run, seed, world.vo_failures))
                if run.stereo is not None and setup.fixes is False:
                    stereo.append({"seed": seed, **run.stereo})
                if seed == 0:
                    example[setup.label] = _track(run)
                bar.update()
        bar.close()
        sweep = spotting_sweep(frames, config.sim, config.sweep_ranges_m, config.sweep_per_range, 0)
    result = {
        "config": asdict(config),
        "rig": rig.names,
        "map": str(map_tif),
        "frames_from": str(frames_tif),
        "odometry": "orthonav.odometry.estimate_motion (orb, homography) on the rendered nadir frames",
        "summary": summarise(rows),
        "spotting": {"flights": spotted, "by_range": sweep},
        "stereo": {"per_seed": stereo, "median": _stereo_median(stereo)},
        "rows": rows,
        "example_seed0": example,
        "machine": watch.record(),
    }
    write_json_atomic(out_json, result)
    plot_slam_bench(result["summary"], example, out_json.with_suffix(".png"))
    return result


def _row(run: SlamRun, seed: int, vo_failures: list[str]) -> dict:
    c = run.counts
    return {
        "setup": run.setup.label,
        "seed": seed,
        **run.metrics(),
        "wrong_tracks": run.wrong_tracks,
        "fixes": f"{c['fixes_used']}/{c['fixes_tried']}",
        "sightings": c["sightings"],
        "pairs_matched": c["pairs_matched"],
        "pairs_refused": c["pairs_refused"],
        "vo_failures": len(vo_failures),
        "seconds": round(run.seconds, 1),
    }


def _track(run: SlamRun) -> dict:
    """UAV 1's estimated and true positions (for the plot)."""
    return {
        "estimate_en": np.round(run.estimate[0][:, :2], 1).tolist(),
        "truth_en": np.round(run.truth[0][:, :2], 1).tolist(),
    }


def summarise(rows: list[dict]) -> list[dict]:
    """Medians over seeds per setup, in the order the setups were run."""
    out = []
    for label in dict.fromkeys(r["setup"] for r in rows):
        group = [r for r in rows if r["setup"] == label]
        used = sum(int(r["fixes"].split("/")[0]) for r in group)
        tried = sum(int(r["fixes"].split("/")[1]) for r in group)
        out.append(
            {
                "setup": label,
                "seeds": len(group),
                "ATE UAV 1 (m)": median((r["ate_m"] for r in group), 2),
                "ATE all UAVs (m)": median((r["ate_all_m"] for r in group), 2),
                "RPE (m)": median((r["rpe_m"] for r in group), 2),
                "landmark error (m)": median((r["landmark_m"] for r in group), 2),
                "landmarks": int(np.median([r["landmarks"] for r in group])),
                "wrong tracks": int(sum(r["wrong_tracks"] for r in group)),
                "fixes used": f"{used}/{tried}" if tried else "-",
                "s per run": median((r["seconds"] for r in group), 2),
            }
        )
    return out


def _stereo_median(per_seed: list[dict]) -> dict | None:
    if not per_seed:
        return None
    return {
        key: {name: median((s[key][name] for s in per_seed), 2) for name in per_seed[0][key]}
        for key in ("distance_error_m", "size_error_pct")
    }
