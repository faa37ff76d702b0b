"""``orthonav bench correction``: correcting an INS error from one frame on real cross-date imagery, and more.

All in one run, on the same frames for every method:
- NAIP (5 m/px): map of one evaluation date, frames rendered from another (every ordered
  pair; training dates are never used), a random initial error of each size in a random
  direction; every backbone at every size, and the keypoint localizer on the same frames
  and priors. Rows: fix rate, mean/min/max/median error of accepted corrections, share
  within 10 m (2 map px), false corrections (accepted, > 5 map px off), time per correction.
- a route: an INS track drifting from the truth, corrected every ``route_every_s`` seconds
  (a correction replaces the INS position); INS alone vs corrected.
- NEON (10 cm, green 2017 vs dry 2018): the same at drone resolution.
Priors carry the autopilot's other estimates with their noise: altitude (baro, +-5 %),
heading (2 deg sigma), pitch/roll (0.3 deg).
"""

from __future__ import annotations

import itertools
import math
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench import scoring
from orthonav.bench.localize import AHRS_SIGMA_DEG, BARO_FRACTION, centre_point, random_pose
from orthonav.bench.machine import LoadWatch
from orthonav.bench.scoring import mean, median, rate, share, wrong_rate
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster, LocalFrame, destination
from orthonav.localize import CorrectionConfig, Corrector, Localizer
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.models import shipped_model_path
from orthonav.types import Prior

FALSE_PX = 5.0
RECOVERED_PX = 2.0


@dataclass(frozen=True)
class CorrectionBenchConfig:
    """Everything that decides the numbers; written beside them."""

    frames: int = 8
    seed: int = 0
    width: int = 640
    height: int = 480
    hfov_deg: float = 60.0
    alt_m: float = 1000.0
    alt_jitter: float = 0.1
    max_tilt_deg: float = 3.0
    heading_sigma_deg: float = 2.0
    photometric: float = 0.6
    initial_errors_m: tuple[float, ...] = (10.0, 15.0, 50.0, 100.0, 200.0)
    search_factor: float = 1.6
    backbones: tuple[str, ...] = ("gradient", "trained", "vgg11", "resnet18", "mobilenetv2")
    sizes: tuple[int, ...] = (224, 448)
    eval_dates: tuple[str, ...] = ("20090818", "20150926", "20200831")
    keypoint_features: tuple[str, ...] = ("orb", "aliked")
    route_length_m: float = 3000.0
    route_speed_mps: float = 15.0
    route_every_s: float = 10.0
    ins_bias_mps: float = 0.15
    ins_walk_mps_per_sqrt_s: float = 0.01
    neon_alt_m: float = 6.0
    neon_errors_m: tuple[float, ...] = (1.0, 2.0, 5.0)
    neon_search_factor: float = 3.0
    model_path: str | None = None

    def __post_init__(self) -> None:
        if self.frames < 1 or not self.initial_errors_m or not self.backbones or not self.sizes:
            raise OrthonavError(
                "bench correction: expected frames >= 1 and at least one error, backbone, size"
            )
        if len(self.eval_dates) < 2:
            raise OrthonavError(f"bench correction eval dates: expected at least two, got {self.eval_dates}")

    @property
    def camera(self) -> Camera:
        return Camera.from_hfov(self.width, self.height, self.hfov_deg)


@dataclass
class _Sample:
    frame: np.ndarray
    truth: TruePose
    centre: tuple[float, float]  # the ground point under the image centre
    priors: dict[float, Prior]  # by initial error (m)


def run_correction_benchmark(
    naip_dir: Path,
    neon_dir: Path | None,
    out_json: Path,
    config: CorrectionBenchConfig = CorrectionBenchConfig(),
    progress: bool = True,
) -> dict:
    """Run every experiment; return and write the results (JSON, PNGs beside it)."""
    from orthonav.models.train import dates_in

    watch = LoadWatch()
    orthos = dates_in(naip_dir, list(config.eval_dates))
    out_json.parent.mkdir(parents=True, exist_ok=True)
    backbones = _available_backbones(config)
    samples = {p: _samples(p, config) for p in orthos}
    pairs = [(m, f) for m, f in itertools.product(orthos, orthos) if m != f]
    records: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="orthonav-bench-") as packages:
        for map_path, frames_path in tqdm(pairs, desc="date pairs", disable=not progress):
            with GeoRaster(map_path) as raster:
                for backbone, size in itertools.product(backbones, config.sizes):
                    corrector = Corrector(
                        raster, config.camera, _correction_config(config, backbone, size, None)
                    )
                    records += _correct_all(corrector, samples[frames_path], config, map_path, frames_path)
            records += _keypoints(Path(packages), map_path, frames_path, samples[frames_path], config)
    rows = _rows(records, _gsd(orthos[0]))
    result = {
        "config": _config_dict(config),
        "model": _model_info(config) if "trained" in backbones else None,
        "rows": rows,
        "speed": _speed(records),
        "route": run_route(
            orthos[-1], orthos[0], backbones, config, out_json.with_name(out_json.stem + "_route.png")
        ),
        "neon": _neon(neon_dir, backbones, config) if neon_dir else None,
        "records": records,
        "machine": watch.record(),
    }
    result["targets"] = _targets(result)
    write_json_atomic(out_json, result)
    _plot(records, out_json.with_suffix(".png"))
    return result


def _available_backbones(config: CorrectionBenchConfig) -> list[str]:
    model = Path(config.model_path) if config.model_path else shipped_model_path()
    return [b for b in config.backbones if b != "trained" or model.is_file()]


def _correction_config(
    config: CorrectionBenchConfig, backbone: str, size: int, factor: float | None
) -> CorrectionConfig:
    return CorrectionConfig(
        backbone=backbone,
        model_path=config.model_path,
        size_px=size,
        search_factor=factor or config.search_factor,
    )


def _gsd(path: Path) -> float:
    with GeoRaster(path) as raster:
        return raster.gsd_m


def _samples(path: Path, config: CorrectionBenchConfig) -> list[_Sample]:
    """Frames at random poses far enough from the edges for the widest search region."""
    camera = config.camera
    rng = np.random.default_rng([config.seed, *path.stem.encode()])
    alt_max = config.alt_m * (1 + config.alt_jitter) * (1 + BARO_FRACTION)
    w_m, h_m = camera.nadir_footprint_m(alt_max)
    reach_m = 0.5 * config.search_factor * math.hypot(w_m, h_m) + max(config.initial_errors_m)
    out = []
    with GeoRaster(path) as raster:
        for _ in range(config.frames):
            truth = random_pose(
                raster,
                camera,
                (config.alt_m, config.alt_m),
                config.alt_jitter,
                config.max_tilt_deg,
                rng,
                margin_px=reach_m / raster.gsd_m + 2,
            )
            frame = render_frame(raster, camera, truth, Photometric.random(rng, config.photometric), rng)
            out.append(
                _Sample(
                    frame,
                    truth,
                    centre_point(camera, truth),
                    {e: _prior(truth, e, config, rng) for e in config.initial_errors_m},
                )
            )
    return out


def _prior(truth: TruePose, error_m: float, config: CorrectionBenchConfig, rng: np.random.Generator) -> Prior:
    lat, lon = destination(truth.lat, truth.lon, rng.uniform(0, 360), error_m)
    return Prior(
        lat,
        lon,
        truth.alt_agl_m * (1.0 + rng.uniform(-BARO_FRACTION, BARO_FRACTION)),
        (truth.yaw_deg + rng.normal(0.0, config.heading_sigma_deg)) % 360.0,
        truth.pitch_deg + rng.normal(0.0, AHRS_SIGMA_DEG),
        truth.roll_deg + rng.normal(0.0, AHRS_SIGMA_DEG),
        sigma_m=max(error_m, 5.0),
        heading_sigma_deg=config.heading_sigma_deg,
    )


def _correct_all(
    corrector: Corrector,
    samples: list[_Sample],
    config: CorrectionBenchConfig,
    map_path: Path,
    frames_path: Path,
) -> list[dict]:
    out = []
    for s in samples:
        for error, prior in s.priors.items():
            fix = corrector.correct(s.frame, prior).fix
            out.append(
                _record(
                    corrector.config.backbone, corrector.config.size_px, error, fix, s, map_path, frames_path
                )
            )
    return out


def _keypoints(
    package_dir: Path,
    map_path: Path,
    frames_path: Path,
    samples: list[_Sample],
    config: CorrectionBenchConfig,
) -> list[dict]:
    """The keypoint localizer on the same frames and priors (maps built once per date and backend)."""
    out = []
    for features in config.keypoint_features:
        target = package_dir / f"{features}-{map_path.stem}"
        tiling = TilingConfig(nominal_alt_m=config.alt_m)
        package = (
            MapPackage(target)
            if target.exists()
            else build_map(map_path, target, config.camera, tiling, features, progress=False)
        )
        localizer = Localizer(package, config.camera)
        for s in samples:
            for error, prior in s.priors.items():
                fix = localizer.localize(s.frame, prior)
                out.append(
                    _record(f"keypoints:{features}", config.width, error, fix, s, map_path, frames_path)
                )
    return out


def _record(
    method: str, size: int, error: float, fix, sample: _Sample, map_path: Path, frames_path: Path
) -> dict:
    """The drone's error (it carries the attitude noise: 0.3 deg at 1000 m is 5 m) and the
    error of the ground point under the image centre (what the matching itself found)."""
    drone = centre = None
    if fix.accepted:
        drone = round(scoring.error_m(sample.truth.lat, sample.truth.lon, fix.pose.lat, fix.pose.lon), 2)
        centre = round(scoring.error_m(*sample.centre, fix.pose.centre_lat, fix.pose.centre_lon), 2)
    return {
        "method": method,
        "size": size,
        "initial_m": error,
        "accepted": fix.accepted,
        "error_m": drone,
        "centre_error_m": centre,
        "ms": round(fix.timings_ms.get("total_ms", math.nan), 1),
        "map": map_path.stem,
        "frames": frames_path.stem,
        "reason": fix.reason,
    }


def _rows(records: list[dict], gsd_m: float) -> list[dict]:
    """One row per (method, size, initial error): the fix rate and the error statistics."""
    key = lambda r: (r["method"], r["size"], r["initial_m"])  # noqa: E731
    rows = []
    for (method, size, initial), group in itertools.groupby(sorted(records, key=key), key=key):
        rows.append({"method": method, "size": size, "initial_m": initial, **_stats(list(group), gsd_m)})
    return rows


def _stats(group: list[dict], gsd_m: float) -> dict:
    n = len(group)
    errors = np.array([r["error_m"] for r in group if r["accepted"]], float)
    centre = np.array([r["centre_error_m"] for r in group if r["accepted"]], float)

    def stat(fn) -> float | None:
        return round(float(fn(errors)), 1) if len(errors) else None

    return {
        "n": n,
        "fix_rate": rate(len(errors), n),
        "mean_m": mean(errors),
        "min_m": stat(np.min),
        "max_m": stat(np.max),
        "median_m": median(errors),
        "within_2px": share(errors <= RECOVERED_PX * gsd_m, n),
        "centre_median_m": median(centre),
        "centre_within_2px": share(centre <= RECOVERED_PX * gsd_m, n),
        "false_rate": wrong_rate(centre, n, FALSE_PX * gsd_m),
        "median_ms": median(r["ms"] for r in group),
    }


def _speed(records: list[dict]) -> list[dict]:
    key = lambda r: (r["method"], r["size"])  # noqa: E731
    return [
        {"method": m, "size": s, "median_ms": median(r["ms"] for r in g)}
        for (m, s), g in ((k, list(g)) for k, g in itertools.groupby(sorted(records, key=key), key=key))
    ]


def run_route(
    map_path: Path, frames_path: Path, backbones: list[str], config: CorrectionBenchConfig, out_png: Path
) -> dict:
    """A straight route through the map's centre; INS alone vs INS corrected every N seconds."""
    from orthonav.viz.correction import plot_route

    camera = config.camera
    rng = np.random.default_rng([config.seed, 7])
    with GeoRaster(map_path) as raster, GeoRaster(frames_path) as frames:
        lat0, lon0 = raster.center_latlon
        centre = LocalFrame(lat0, lon0)
        heading = float(rng.uniform(0, 360))
        truth_en, ins_en = _ins_track(config, heading, rng)
        tracks = {"truth": truth_en, "INS alone": ins_en}
        stats = {
            "INS alone": {
                **_deviation(truth_en, ins_en),
                "corrections_accepted": 0,
                "corrections_rejected": 0,
            }
        }
        for backbone in backbones:
            corrector = Corrector(raster, camera, _correction_config(config, backbone, 224, None))
            corrected, fixes = _corrected_track(
                corrector, frames, centre, truth_en, ins_en, heading, config, rng
            )
            tracks[f"corrected ({backbone})"] = corrected
            stats[f"corrected ({backbone})"] = {**_deviation(truth_en, corrected), **fixes}
        plot_route(raster, centre, tracks, out_png)
    return {
        "map": map_path.stem,
        "frames": frames_path.stem,
        "heading_deg": round(heading, 1),
        "stats": stats,
    }


def _ins_track(
    config: CorrectionBenchConfig, heading_deg: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """1 s samples of the true track (ENU around the map centre) and the drifting INS track."""
    duration = config.route_length_m / config.route_speed_mps
    t = np.arange(0.0, duration + 1.0)
    h = math.radians(heading_deg)
    along = (t - duration / 2.0) * config.route_speed_mps
    truth = np.column_stack([along * math.sin(h), along * math.cos(h)])
    bias = rng.normal(0.0, config.ins_bias_mps, 2)
    walk = np.cumsum(rng.normal(0.0, config.ins_walk_mps_per_sqrt_s, (len(t), 2)), axis=0)
    drift_velocity = bias + walk
    drift = np.vstack([[0.0, 0.0], np.cumsum(drift_velocity[:-1], axis=0)])
    return truth, truth + drift


def _corrected_track(
    corrector: Corrector,
    frames: GeoRaster,
    centre: LocalFrame,
    truth_en: np.ndarray,
    ins_en: np.ndarray,
    heading_deg: float,
    config: CorrectionBenchConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, dict]:
    """INS increments from the last accepted correction on (a correction resets the INS)."""
    every = max(1, round(config.route_every_s))
    estimate = ins_en.copy()
    accepted = rejected = 0
    for i in range(every, len(truth_en), every):
        lat, lon = (float(v) for v in centre.to_latlon(*truth_en[i]))
        truth = TruePose(lat, lon, config.alt_m, heading_deg)
        frame = render_frame(
            frames, corrector.camera, truth, Photometric.random(rng, config.photometric), rng
        )
        plat, plon = (float(v) for v in centre.to_latlon(*estimate[i]))
        prior = Prior(
            plat,
            plon,
            config.alt_m,
            (heading_deg + rng.normal(0, config.heading_sigma_deg)) % 360,
            heading_sigma_deg=config.heading_sigma_deg,
        )
        try:
            fix = corrector.correct(frame, prior).fix
        except OrthonavError:
            fix = None  # the estimate left the map: nothing to correct against
        if fix is not None and fix.accepted:
            accepted += 1
            fixed = np.array([float(v) for v in centre.to_enu(fix.pose.lat, fix.pose.lon)])
            estimate[i:] += fixed - estimate[i]
        else:
            rejected += 1
    return estimate, {"corrections_accepted": accepted, "corrections_rejected": rejected}


def _deviation(truth: np.ndarray, track: np.ndarray) -> dict:
    d = np.hypot(*(track - truth).T)
    return {
        "max_m": round(float(d.max()), 1),
        "mean_m": round(float(d.mean()), 1),
        "final_m": round(float(d[-1]), 1),
    }


def _neon(neon_dir: Path, backbones: list[str], config: CorrectionBenchConfig) -> dict | None:
    """Cross-season plots at 10 cm: frames of one year against the map of the other."""
    years = sorted(p for p in neon_dir.iterdir() if p.is_dir())
    if len(years) != 2:
        return None
    names = sorted({p.name for p in years[0].glob("*.tif")} & {p.name for p in years[1].glob("*.tif")})
    neon = replace(
        config,
        alt_m=config.neon_alt_m,
        initial_errors_m=config.neon_errors_m,
        max_tilt_deg=2.0,
        alt_jitter=0.03,
        search_factor=config.neon_search_factor,
    )
    records = []
    for name in names:
        for frames_year, map_year in ((years[0], years[1]), (years[1], years[0])):
            sample = _centre_sample(
                frames_year / name, neon, np.random.default_rng([config.seed, *name.encode()])
            )
            with GeoRaster(map_year / name) as raster:
                for backbone in backbones:
                    corrector = Corrector(
                        raster, neon.camera, _correction_config(neon, backbone, 224, neon.search_factor)
                    )
                    records += _correct_all(corrector, [sample], neon, map_year / name, frames_year / name)
    return {"plots": len(names), "rows": _rows(records, _gsd(years[0] / names[0])), "records": records}


def _centre_sample(path: Path, config: CorrectionBenchConfig, rng: np.random.Generator) -> _Sample:
    """A frame near the centre of a small plot (the search region must fit on it)."""
    with GeoRaster(path) as raster:
        lat, lon = raster.center_latlon
        lat, lon = destination(lat, lon, rng.uniform(0, 360), rng.uniform(0, 0.3))
        tilt = config.max_tilt_deg
        truth = TruePose(
            lat,
            lon,
            config.alt_m * rng.uniform(0.95, 1.05),
            rng.uniform(0, 360),
            rng.uniform(-tilt, tilt),
            rng.uniform(-tilt, tilt),
        )
        frame = render_frame(raster, config.camera, truth, Photometric.random(rng, config.photometric), rng)
    priors = {e: _prior(truth, e, config, rng) for e in config.initial_errors_m}
    return _Sample(frame, truth, centre_point(config.camera, truth), priors)


def _targets(result: dict) -> dict[str, bool]:
    """The issue's targets, checked on the best backbone for each (named in the key)."""
    rows = [r for r in result["rows"] if not r["method"].startswith("keypoints")]

    def best(initial: float, metric: str, lowest: bool = False) -> tuple[str, float]:
        candidates = [r for r in rows if r["initial_m"] == initial and r[metric] is not None]
        if not candidates:
            return "none", math.inf if lowest else 0.0
        pick = (min if lowest else max)(candidates, key=lambda r: r[metric])
        return f"{pick['method']}-{pick['size']}", pick[metric]

    out = {}
    for initial in (10.0, 15.0):
        name, value = best(initial, "mean_m", lowest=True)
        out[f"mean error < 10 m from {initial:.0f} m ({name}: {value} m)"] = value < 10.0
    for metric, what in (("within_2px", "drone"), ("centre_within_2px", "image centre")):
        name, value = best(100.0, metric)
        out[f">= 80 % {what} within 10 m from 100 m ({name}: {value:.0%})"] = value >= 0.8
        name, value = best(200.0, metric)
        out[f">= 90 % {what} within 10 m with a 200 m prior ({name}: {value:.0%})"] = value >= 0.9
    false = max((r["false_rate"] for r in rows if r["method"] in ("gradient", "trained")), default=1.0)
    out[f"false corrections < 1 % (gradient, trained: worst {false:.1%})"] = false < 0.01
    fast = [r for r in result["speed"] if r["size"] == 224 and not r["method"].startswith("keypoints")]
    quick = min(fast, key=lambda r: r["median_ms"]) if fast else {"method": "none", "median_ms": math.inf}
    out[f"< 100 ms per correction at 224 ({quick['method']}: {quick['median_ms']} ms)"] = (
        quick["median_ms"] < 100
    )
    if result["neon"]:
        neon = [r for r in result["neon"]["rows"] if r["initial_m"] == 2.0 and r["mean_m"] is not None]
        pick = min(neon, key=lambda r: r["mean_m"]) if neon else {"method": "none", "mean_m": math.inf}
        out[f"NEON mean error < 0.5 m from 2 m ({pick['method']}: {pick['mean_m']} m)"] = pick["mean_m"] < 0.5
    return out


def _model_info(config: CorrectionBenchConfig) -> dict:
    from orthonav.models.trunks import load_model

    _, info = load_model(config.model_path or shipped_model_path())
    return {
        "path": str(config.model_path or shipped_model_path().name),
        "dates": info.get("dates"),
        "validation": info.get("validation"),
    }


def _config_dict(config: CorrectionBenchConfig) -> dict:
    return {**asdict(config), "time": time.strftime("%Y-%m-%d %H:%M:%S")}


def _plot(records: list[dict], out: Path) -> None:
    """Error distributions from the largest initial error up to 100 m."""
    from orthonav.viz.localize import plot_error_cdf

    sizes = {r["initial_m"] for r in records}
    initial = max((e for e in sizes if e <= 100.0), default=max(sizes, default=0.0))
    errors: dict[str, tuple[list[float], int]] = {}
    for r in records:
        if r["initial_m"] != initial:
            continue
        label = f"{r['method']} {r['size']}"
        accepted, n = errors.get(label, ([], 0))
        errors[label] = (accepted + ([r["error_m"]] if r["accepted"] else []), n + 1)
    title = f"orthonav bench correction: error after correcting a {initial:.0f} m INS error"
    plot_error_cdf(errors, out, title)
