"""``orthonav bench localize``: accuracy, honesty and speed of the localizer on real imagery.

Conditions, all in one run:
- cross-date: map from one year, frames rendered from another (every ordered year pair of
  a folder of co-registered GeoTIFFs), with a prior and without one (and, where asked, with
  the prior's position but no heading: a compass that failed; or with the heading but no
  position: lost with a working compass, the companion's lost prior);
- same-date: map and frames from the same orthophoto (the easy case), on the
  same folder and on drone-scale orthophotos with the camera at 50-150 m.

Methods side by side on the same frames and priors: ``keypoints`` (the :class:`Localizer`),
``correlation`` (dense gradient correlation over the prior's window, with its own gates) and
``cascade`` (candidates -> correlation -> keypoints -> verification -> calibrated acceptance).

"With prior" = position within ``prior_radius_m``, heading within ``heading_prior_deg``; "no
heading" = that position without the heading; "no position" = that heading without the
position; "no prior" = neither.
Altitude (barometer, +-5 %) and roll/pitch (AHRS, 0.3 deg noise) are given in every
condition: an autopilot always has them. The truth for the frame-centre error is the
ground point under the image centre; the drone error is the point under the camera.
"""

from __future__ import annotations

import functools
import itertools
import resource
import tempfile
from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.bench.calibration import calibration_table
from orthonav.bench.machine import LoadWatch
from orthonav.bench.scoring import (
    error_enu_m,
    error_m,
    mean,
    mean_per_frame,
    median,
    nees,
    rate,
    share,
    sigma_coverage,
    sigma_targets,
    within_rates,
    wrong_rate,
)
from orthonav.bench.sizes import run_speed_table
from orthonav.camera import Camera, CameraPose, pixel_to_ground
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, Runtime, available_backends
from orthonav.frames import Photometric, TruePose, render_frame, sees_only_ground
from orthonav.frames.relief import Relief, render_relief_frame
from orthonav.geo import GeoRaster, LocalFrame, PixelWindow, bright_pixels, destination
from orthonav.localize import (
    CASCADE,
    CORRELATION,
    DEFAULT_COARSE_BACKBONE,
    FIX_SOURCES,
    KEYPOINTS,
    CandidatesStage,
    CoarseConfig,
    CoarseStage,
    CorrectionConfig,
    coarse_backbones,
    make_fix_source,
)
from orthonav.mapdb import INDEX_METHODS, MapPackage, TilingConfig, build_global_index, build_map
from orthonav.types import Fix, FixSource, Prior, footprint_latlon
from orthonav.viz.calibration import plot_reliability
from orthonav.viz.localize import plot_error_cdf, plot_pair_matrix

FALSE_FIX_M = 50.0
WRONG_M = 25.0
# The cascade's target share of frame centres within 10 m, on every cross-date pair.
PAIR_TARGET = 0.9
CLASSICAL = {"orb", "sift"}
CROSS, SAME = "cross-date", "same-date"
PRIOR, NO_HEADING, NO_POSITION, NO_PRIOR = "prior", "no heading", "no position", "no prior"
PRIOR_MODES = (PRIOR, NO_HEADING, NO_POSITION, NO_PRIOR)
# Lost (no position): searched through the map's global index, cross-date frames only.
LOST_MODES = (NO_POSITION, NO_PRIOR)
AHRS_SIGMA_DEG = 0.3
BARO_FRACTION = 0.05


@dataclass(frozen=True)
class LocalizeBenchConfig:
    """Everything that decides a benchmark's numbers; written beside them."""

    frames: int = 20
    seed: int = 0
    width: int = 640
    height: int = 480
    hfov_deg: float = 60.0
    alt_m: float = 1000.0
    highres_alt_m: tuple[float, float] = (50.0, 150.0)
    # Boxes of these heights (m) standing on the drone-scale maps' ground in their frames: houses
    # and trees that a flat-ground pose cannot see (frames.relief); None: flat ground.
    highres_relief_m: tuple[float, float] | None = None
    alt_jitter: float = 0.2
    # Each frame's pitch and roll, uniform within +- this: a gimbal's residual at the default, a
    # body camera's 20-30 deg in a copter's acceleration or a plane's bank beyond.
    max_tilt_deg: float = 5.0
    # The 1-sigma error of the roll and pitch the priors carry; the priors claim AHRS_SIGMA_DEG
    # whatever it is, as fly assumes of an autopilot, so a larger one is an attitude worse than
    # claimed (an autopilot whose tilt follows the fixes it is sent).
    attitude_noise_deg: float = AHRS_SIGMA_DEG
    prior_radius_m: float = 200.0
    heading_prior_deg: float = 10.0
    photometric: float = 1.0
    features: tuple[str, ...] = ("orb",)
    speed_sizes: tuple[int, ...] = (320, 640, 1024)
    speed_repeats: int = 5
    methods: tuple[str, ...] = (KEYPOINTS,)
    # The cascade's coarse correlations (fly's --coarse-backbone): gradient>orientation by default.
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE
    # The cascade's CascadeConfig.trunk_check (None: where its acceptance model weighs the trunk).
    trunk_check: bool | None = None
    # What the frames' priors know (PRIOR_MODES); same-date frames are never searched lost.
    priors: tuple[str, ...] = (PRIOR, NO_PRIOR)
    # A global index (vlad, cnn) on every map of the folder, which lost frames are searched
    # through; None: none (lost frames are matched against every tile).
    global_index: str | None = None

    def __post_init__(self) -> None:
        unknown = set(self.features) - set(available_backends())
        if unknown or not self.features:
            raise OrthonavError(
                f"bench features {sorted(unknown)}: expected names from {', '.join(available_backends())}"
            )
        if not self.methods or not set(self.methods) <= set(FIX_SOURCES):
            raise OrthonavError(
                f"bench methods {list(self.methods)}: expected some of {', '.join(FIX_SOURCES)}"
            )
        unknown_priors = [mode for mode in self.priors if mode not in PRIOR_MODES]
        if unknown_priors or not self.priors:
            raise OrthonavError(f"bench priors {unknown_priors}: expected some of {', '.join(PRIOR_MODES)}")
        if self.global_index not in (None, *INDEX_METHODS):
            raise OrthonavError(
                f"bench global index {self.global_index!r}: expected one of {', '.join(INDEX_METHODS)}"
            )
        coarse_backbones(self.coarse_backbone)
        tilts = itertools.product((-self.max_tilt_deg, self.max_tilt_deg), repeat=2)
        if not self.max_tilt_deg >= 0.0 or not all(
            sees_only_ground(self.camera, TruePose(0.0, 0.0, 1.0, 0.0, pitch, roll)) for pitch, roll in tilts
        ):
            raise OrthonavError(
                f"bench max tilt {self.max_tilt_deg:g} deg: expected 0 or more, and little enough that a "
                f"{self.hfov_deg:g} deg camera tilted so in pitch and roll sees no horizon"
            )
        if not 0.0 <= self.attitude_noise_deg <= 10.0:
            raise OrthonavError(
                f"bench attitude noise {self.attitude_noise_deg:g} deg: expected 0 to 10 deg (1-sigma)"
            )

    @property
    def camera(self) -> Camera:
        return Camera.from_hfov(self.width, self.height, self.hfov_deg)


@dataclass
class Sample:
    """A rendered frame, its true pose and image centre, and its priors (with and without position)."""

    frame: np.ndarray
    truth: TruePose
    centre: tuple[float, float]
    prior: Prior
    blind: Prior


def run_localize_benchmark(
    data_dir: Path,
    highres_dir: Path | None,
    out_json: Path,
    config: LocalizeBenchConfig = LocalizeBenchConfig(),
    progress: bool = True,
    runtime: Runtime | None = None,
    backend_conf: dict[str, dict] | None = None,
) -> dict:
    """Run every condition for every backend on the same frames; return and write the results.

    ``backend_conf`` holds per-backend config (e.g. superpoint's weight files); ``runtime``
    where learned backends run.
    """
    watch = LoadWatch()
    backend_conf = backend_conf or {}
    years = sorted(data_dir.glob("*.tif"))
    if not years:
        raise OrthonavError(f"{data_dir}: no GeoTIFFs to benchmark on")
    highres = sorted(highres_dir.glob("*.tif")) if highres_dir else []
    camera = config.camera
    band = (config.alt_m, config.alt_m)
    samples = {p: render_samples(p, camera, band, config) for p in years}
    relief = Relief(heights_m=config.highres_relief_m) if config.highres_relief_m else None
    samples |= {p: render_samples(p, camera, config.highres_alt_m, config, relief) for p in highres}
    same_date_modes = [mode for mode in config.priors if mode not in LOST_MODES]
    jobs = [
        (map_p, frames_p, mode)
        for map_p, frames_p in itertools.product(years, years)
        for mode in (same_date_modes if map_p == frames_p else config.priors)
    ]
    jobs += [(p, p, PRIOR) for p in highres if PRIOR in config.priors]
    rows: list[dict] = []
    errors: dict[str, tuple[list[float], int]] = {}
    with tempfile.TemporaryDirectory(prefix="orthonav-bench-") as tmp, ExitStack() as stack:
        needs_raster = set(config.methods) != {KEYPOINTS}
        rasters = {p: stack.enter_context(GeoRaster(p)) for p in [*years, *highres]} if needs_raster else {}
        for backend in config.features:
            conf = backend_conf.get(backend, {})
            build = functools.partial(
                build_bench_map, tmp=Path(tmp), camera=camera, backend=backend, conf=conf, runtime=runtime
            )
            maps = {p: build(p, config.alt_m, index=config.global_index) for p in years}
            # Drone-scale maps are built for the geometric middle of the altitude band.
            maps |= {p: build(p, float(np.sqrt(np.prod(config.highres_alt_m)))) for p in highres}
            # One backend instance (models loaded once) serves every map it built.
            features = next(iter(maps.values())).create_backend(runtime)
            sources = {
                (method, p): _fix_source(method, maps[p], rasters.get(p), camera, features, config)
                for method in config.methods
                for p in maps
            }
            for map_p, frames_p, mode in tqdm(jobs, desc=f"bench localize {backend}", disable=not progress):
                condition = SAME if map_p == frames_p else CROSS
                condition += (" high-res" + (" relief" if relief else "")) if map_p in highres else ""
                for method in config.methods:
                    row = evaluate_samples(sources[method, map_p], maps[map_p].gsd_m, samples[frames_p], mode)
                    row.update(
                        features=backend,
                        method=method,
                        map=map_p.stem,
                        frames_from=frames_p.stem,
                        condition=condition,
                        prior=mode,
                    )
                    rows.append(row)
                    label = f"{backend}{_method_label(method)} {condition} {mode}"
                    found, tried = errors.get(label, ([], 0))
                    errors[label] = (found + row["errors_m"], tried + row["n"])
    speed_image = (highres or years)[-1]
    speed = (
        run_speed_table(
            speed_image,
            config.features,
            config.speed_sizes,
            repeats=config.speed_repeats,
            runtime=runtime,
            backend_conf=backend_conf,
        )
        if config.speed_sizes
        else []
    )
    result = {
        "config": asdict(config),
        "runtime": asdict(runtime or Runtime()),
        "data": str(data_dir),
        "rows": rows,
        "summary": _summary(rows),
        "speed": {"image": str(speed_image), "rows": speed},
        "peak_rss_mb": _peak_rss_mb(),
        "machine": watch.record((runtime or Runtime()).threads),
    }
    write_json_atomic(out_json, result)
    plot_error_cdf(errors, out_json.with_suffix(".png"), "orthonav bench localize: drone position error")
    pairs: dict[str, list[dict]] = {}  # the cross-date pairs with a prior, by what ran
    for row in rows:
        if (row["condition"], row["prior"]) == (CROSS, PRIOR):
            pairs.setdefault(_group(row).split(":")[0], []).append(row)
    if pairs:
        plot_pair_matrix(pairs, out_json.with_name(f"{out_json.stem}_pairs.png"), PAIR_TARGET)
    for group, pooled in result["summary"].items():
        if group.endswith(f"{CROSS} / {PRIOR}") and pooled.get("calibration", {}).get("bins"):
            name = group.split(":")[0].replace(" ", "_")
            png = out_json.with_name(f"{out_json.stem}_reliability_{name}.png")
            plot_reliability(pooled["calibration"], png, f"{out_json.name}: {group}, accepted fixes")
    return result


def build_bench_map(
    path: Path,
    alt: float,
    tmp: Path,
    camera: Camera,
    backend: str,
    conf: dict,
    runtime: Runtime | None,
    index: str | None = None,
) -> MapPackage:
    """The backend's map of ``path`` for ``alt`` in ``tmp``, with a global index of the
    ``index`` method where asked; one already there is reused."""
    out = tmp / f"{backend}-{path.stem}"
    if (out / "manifest.json").is_file():
        package = MapPackage(out)
    else:
        tiling = TilingConfig(nominal_alt_m=alt)
        package = build_map(path, out, camera, tiling, backend, conf, progress=False, runtime=runtime)
    if index is None or (package.manifest.get("global_index") or {}).get("method") == index:
        return package
    return build_global_index(package, method=index)


def render_samples(
    path: Path,
    camera: Camera,
    alt_range: tuple[float, float],
    config: LocalizeBenchConfig,
    relief: Relief | None = None,
) -> list[Sample]:
    """Random poses whose footprint lies inside the orthophoto, seeded per file name; with
    ``relief``'s boxes on the ground where given."""
    rng = np.random.default_rng([config.seed, *path.stem.encode()])
    out = []
    with GeoRaster(path) as raster:
        for _ in range(config.frames):
            truth = random_pose(raster, camera, alt_range, config.alt_jitter, config.max_tilt_deg, rng)
            photometric = Photometric.random(rng, config.photometric)
            if relief is None:
                frame = render_frame(raster, camera, truth, photometric, rng)
            else:
                frame = render_relief_frame(raster, camera, truth, relief, photometric, rng)
            out.append(Sample(frame, truth, centre_point(camera, truth), *_priors(truth, config, rng)))
    return out


def random_pose(
    raster: GeoRaster,
    camera: Camera,
    alt_range: tuple[float, float],
    alt_jitter: float,
    max_tilt_deg: float,
    rng: np.random.Generator,
    margin_px: float = 0.0,
) -> TruePose:
    """A random pose whose footprint lies on imagery, ``margin_px`` or more from the edges."""
    for _ in range(1000):
        alt = rng.uniform(*alt_range) * rng.uniform(1 - alt_jitter, 1 + alt_jitter)
        col = rng.uniform(margin_px, raster.width - margin_px)
        row = rng.uniform(margin_px, raster.height - margin_px)
        lat, lon = (float(v) for v in raster.pixel_to_latlon(col, row))
        tilt = max_tilt_deg
        pose = TruePose(
            lat, lon, alt, rng.uniform(0, 360), rng.uniform(-tilt, tilt), rng.uniform(-tilt, tilt)
        )
        corners = footprint_latlon(camera, lat, lon, alt, pose.yaw_deg, pose.pitch_deg, pose.roll_deg)
        clat, clon = corners[:, 0], corners[:, 1]
        if all(raster.contains_latlon(a, b) for a, b in zip(clat, clon, strict=True)) and _has_imagery(
            raster, *raster.latlon_to_pixel(clat, clon)
        ):
            return pose
    raise OrthonavError(
        f"{raster.path}: too small for a {camera.width}x{camera.height} frame at {alt_range} m"
    )


def _has_imagery(raster: GeoRaster, cols: np.ndarray, rows: np.ndarray) -> bool:
    """No more than 2 % nodata under the footprint: no real camera sees the map's empty corners."""
    c0, r0 = int(cols.min()), int(rows.min())
    window = PixelWindow(c0, r0, max(1, int(cols.max()) - c0), max(1, int(rows.max()) - r0))
    return float(np.mean(~bright_pixels(raster.read_rgb(window, out_shape=(48, 48))))) <= 0.02


def centre_point(camera: Camera, truth: TruePose) -> tuple[float, float]:
    """The true ground point under the image centre (independent of any localizer)."""
    pose = CameraPose(0.0, 0.0, truth.alt_agl_m, truth.yaw_deg, truth.pitch_deg, truth.roll_deg)
    east, north = pixel_to_ground(camera, pose, np.array([[camera.cx, camera.cy]]))[0]
    lat, lon = LocalFrame(truth.lat, truth.lon).to_latlon(east, north)
    return float(lat), float(lon)


def _priors(truth: TruePose, config: LocalizeBenchConfig, rng: np.random.Generator) -> tuple[Prior, Prior]:
    """(with position and heading, without) - both with baro altitude and AHRS attitude."""
    alt = truth.alt_agl_m * (1.0 + rng.uniform(-BARO_FRACTION, BARO_FRACTION))
    attitude = {
        "pitch_deg": truth.pitch_deg + rng.normal(0, config.attitude_noise_deg),
        "roll_deg": truth.roll_deg + rng.normal(0, config.attitude_noise_deg),
    }
    radius = config.prior_radius_m * np.sqrt(rng.uniform())
    lat, lon = destination(truth.lat, truth.lon, rng.uniform(0, 360), radius)
    heading = (truth.yaw_deg + rng.uniform(-config.heading_prior_deg, config.heading_prior_deg)) % 360
    prior = Prior(
        lat,
        lon,
        alt,
        heading,
        sigma_m=config.prior_radius_m / 2.0,
        heading_sigma_deg=config.heading_prior_deg / 2.0,
        **attitude,
    )
    return prior, Prior(alt_agl_m=alt, **attitude)


class _Correlation:
    """Dense gradient correlation alone, with the Corrector's own gates, over the window the
    cascade would search (the prior's position +- 2.5 sigma): the cascade's coarse stage alone."""

    def __init__(self, raster: GeoRaster, camera: Camera) -> None:
        self.windows = CandidatesStage(camera)
        self.coarse = CoarseStage(raster, camera, CoarseConfig(correction=CorrectionConfig()))

    def localize(self, frame: np.ndarray, prior: Prior, candidates: np.ndarray | None = None) -> Fix:
        try:
            window = self.windows.windows(frame, prior)[0]
        except OrthonavError as exc:
            return Fix(False, str(exc), method=self.coarse.corrector.method)
        return self.coarse.localize(frame, window)


def _fix_source(
    method: str,
    package: MapPackage,
    raster: GeoRaster | None,
    camera: Camera,
    features: FeatureBackend,
    config: LocalizeBenchConfig,
) -> FixSource:
    if method == CORRELATION:
        return _Correlation(raster, camera)
    return make_fix_source(
        method,
        package,
        camera,
        raster,
        backend=features,
        coarse_backbone=config.coarse_backbone,
        trunk_check=config.trunk_check,
    )


def _method_label(method: str) -> str:
    """How rows of a method are named in pooled keys and plots (the keypoint rows as before)."""
    return "" if method == KEYPOINTS else f" {method}"


def evaluate_samples(source: FixSource, gsd_m: float, samples: list[Sample], mode: str) -> dict:
    errors, centre_errors, sigmas, timings, keypoints, inliers, matches = [], [], [], [], [], [], []
    nees_values = []
    p_correct = []  # the cascade's P(right) of each accepted fix, in the order of ``errors``
    placed = []  # the centre error of every pose found, accepted or not
    for s in samples:
        fix = source.localize(s.frame, _prior_for(s, mode))
        timings.append(fix.timings_ms)
        if "keypoints" in fix.quality:
            keypoints.append(fix.quality["keypoints"])
        if fix.pose is not None:
            placed.append(error_m(*s.centre, fix.pose.centre_lat, fix.pose.centre_lon))
        if not fix.accepted:
            continue
        errors.append(error_m(s.truth.lat, s.truth.lon, fix.pose.lat, fix.pose.lon))
        centre_errors.append(placed[-1])
        sigmas.append(fix.sigma_m)
        truth = (s.truth.lat, s.truth.lon)
        nees_values.append(nees(fix, error_enu_m(LocalFrame(*truth), truth, (fix.pose.lat, fix.pose.lon))))
        for name, values in (("inliers", inliers), ("matches", matches), ("p_correct", p_correct)):
            if name in fix.quality:
                values.append(fix.quality[name])
    counts = {"keypoints": keypoints, "matches": matches, "inliers": inliers}
    row = _metrics(len(samples), gsd_m, errors, centre_errors, timings, counts)
    row |= sigma_coverage(errors, sigmas, nees_values)
    row |= {"sigmas_m": [round(x, 2) for x in sigmas], "nees": [round(x, 2) for x in nees_values]}
    # What a perfect decision on these poses would fix: the gap to ``centre_within_10m`` is the
    # decision's (right poses rejected), the rest the placement's.
    row["placed_centre_within_10m"] = share((e <= 10.0 for e in placed), len(samples))
    if len(p_correct) == len(errors) > 0:
        row["p_correct"] = [round(float(p), 5) for p in p_correct]
    return row


def _prior_for(sample: Sample, mode: str) -> Prior:
    """The prior a frame is localized with in ``mode`` (one of PRIOR_MODES)."""
    if mode == NO_PRIOR:
        return sample.blind
    if mode == NO_POSITION:
        prior = sample.prior
        return replace(sample.blind, heading_deg=prior.heading_deg, heading_sigma_deg=prior.heading_sigma_deg)
    return sample.prior if mode == PRIOR else replace(sample.prior, heading_deg=None)


def _metrics(
    n: int,
    gsd_m: float,
    errors: list[float],
    centre_errors: list[float],
    timings: list[dict],
    counts: dict[str, list[float]],
) -> dict:
    """Rates are shares of all frames; ``counts`` medians (keypoints per frame, matches and
    inliers per accepted fix); ``stage_ms`` the median of every timing the fixes report."""
    e, c = np.array(errors), np.array(centre_errors)

    def timing(key: str) -> float | None:
        return median(t[key] for t in timings if key in t)

    return {
        "n": n,
        "fix_rate": rate(len(e), n),
        **within_rates(e, n, (5.0, 10.0, 25.0)),
        **within_rates(c, n, (5.0, 10.0, 25.0), prefix="centre_within_"),
        "centre_within_2px": share(c <= 2.0 * gsd_m, n),
        "median_m": median(e),
        "mean_m": mean(e),
        "centre_median_m": median(c),
        "false_fix_rate": wrong_rate(e, n, FALSE_FIX_M),
        "false_25m_rate": wrong_rate(e, n, WRONG_M),
        **{name: median(values, 0) for name, values in counts.items()},
        "extract_ms": timing("extract_ms"),
        "match_ms": timing("match_ms"),
        "pose_ms": timing("pose_ms"),
        "total_ms": timing("total_ms"),
        "stage_ms": {key: timing(key) for key in dict.fromkeys(k for t in timings for k in t)},
        "mean_stage_ms": mean_per_frame(timings),
        "map_gsd_m": round(gsd_m, 3),
        "errors_m": [round(x, 2) for x in errors],
    }


POOLED = (
    "fix_rate",
    "within_5m",
    "within_10m",
    "within_25m",
    "centre_within_5m",
    "centre_within_10m",
    "centre_within_25m",
    "centre_within_2px",
    "placed_centre_within_10m",
    "false_25m_rate",
    "false_fix_rate",
)


def _summary(rows: list[dict]) -> dict:
    """Pooled numbers per condition, and the ORB path's targets checked."""
    out = {}
    for key, group in itertools.groupby(sorted(rows, key=_group), key=_group):
        g = list(group)
        n = sum(r["n"] for r in g)

        def pooled(metric: str, rows_: list[dict] = g, total: int = n) -> float:
            return round(sum(r[metric] * r["n"] for r in rows_) / total, 3)

        out[key] = {
            "n": n,
            **{m: pooled(m) for m in POOLED},
            "median_total_ms": median((r["total_ms"] for r in g), digits=None),
            "stage_ms": _pooled_stages(g),
        }
        out[key] |= _pooled_coverage(g)
        if any("p_correct" in r for r in g):
            out[key]["calibration"] = _calibration(g)
    out["targets"] = _targets(rows, out)
    return out


def _pooled_coverage(rows: list[dict]) -> dict:
    """The sigma figures over every accepted fix of ``rows``, and whether they meet the targets."""
    pooled = sigma_coverage(
        *([v for r in rows for v in r.get(k, [])] for k in ("errors_m", "sigmas_m", "nees"))
    )
    return pooled | {"sigma_targets": sigma_targets(pooled)}


def _calibration(rows: list[dict]) -> dict:
    """The accepted fixes' P(right) against how often they were right (the drone within
    ``WRONG_M``, as the acceptance model was fitted), pooled over ``rows``."""
    p = np.array([v for r in rows for v in r.get("p_correct", [])])
    right = np.array([e <= WRONG_M for r in rows if "p_correct" in r for e in r["errors_m"]])
    return {"of": "the accepted fixes, pooled", **calibration_table(p, right)}


def _targets(rows: list[dict], pooled: dict) -> dict[str, bool]:
    """The targets of what ran: the ORB keypoint path's, each learned backend's keypoints', each
    cascade's (issue targets with a prior: the frame centre within 10 m on every cross-date pair
    and on same-date frames, false fixes, time; without a prior, 70 % within 25 m)."""
    targets = {"false-fix rate < 1 % everywhere": all(r["false_fix_rate"] < 0.01 for r in rows)}
    same = [v for k, v in pooled.items() if k.startswith(f"orb: {SAME}")]
    if same:
        targets["orb same-date centre within 2 map px >= 98 %"] = all(
            v["centre_within_2px"] >= 0.98 for v in same
        )
        targets["orb same-date median time <= 50 ms"] = all(
            (v["median_total_ms"] or np.inf) <= 50 for v in same
        )
    keypoints = {r["features"] for r in rows if r.get("method", KEYPOINTS) == KEYPOINTS}
    for backend in sorted(keypoints - CLASSICAL):
        targets |= _learned_targets(backend, pooled)
    for backend in sorted({r["features"] for r in rows if r.get("method") == CASCADE}):
        targets |= _cascade_targets(backend, pooled, rows)
    return targets


def _cascade_targets(backend: str, pooled: dict, rows: list[dict]) -> dict[str, bool]:
    """The cascade's targets of the conditions that ran (none listed for one that did not)."""
    name = f"{backend} cascade"
    ran = [r for r in rows if r["features"] == backend and r.get("method") == CASCADE]
    pairs = [r for r in ran if (r["condition"], r["prior"]) == (CROSS, PRIOR)]
    cross, same = pooled.get(f"{name}: {CROSS} / prior"), pooled.get(f"{name}: {SAME} / prior")
    lost = pooled.get(f"{name}: {CROSS} / no prior")
    out = {}
    if cross is not None:
        every_pair = all(r["centre_within_10m"] >= PAIR_TARGET for r in pairs)
        few_false = cross["false_25m_rate"] < 0.005 and (same is None or same["false_25m_rate"] == 0.0)
        calibrated = cross.get("calibration", {}).get("within_tolerance", False)
        out[f"{name} frame centre within 10 m >= 90 % on every cross-date pair"] = every_pair
        out[f"{name} false fixes (> 25 m) < 0.5 % across dates, none same-date"] = few_false
        out[f"{name} median time with a prior <= 300 ms"] = (cross["median_total_ms"] or np.inf) <= 300
        out[f"{name} P(right) within 5 points of the observed rate per decile, across dates"] = calibrated
    if same is not None:
        out[f"{name} same-date frame centre within 10 m >= 97 %"] = same["centre_within_10m"] >= 0.97
    if lost is not None:
        out[f"{name} without a prior within 25 m >= 70 % across dates"] = lost["within_25m"] >= 0.7
    return out


def _learned_targets(backend: str, pooled: dict) -> dict[str, bool]:
    """The learned-feature targets, checked per backend (with priors, as specified)."""
    cross = pooled.get(f"{backend}: cross-date / prior")
    same = [v for k, v in pooled.items() if k.startswith(f"{backend}: same-date")]
    return {
        f"{backend} cross-date within 25 m >= 50 %": bool(cross) and cross["within_25m"] >= 0.5,
        f"{backend} same-date centre within 2 map px >= 99 %": bool(same)
        and all(v["centre_within_2px"] >= 0.99 for v in same),
        f"{backend} median time <= 400 ms": bool(same)
        and all((v["median_total_ms"] or np.inf) <= 400 for v in same),
    }


def _group(row: dict) -> str:
    method = _method_label(row.get("method", KEYPOINTS))
    return f"{row['features']}{method}: {row['condition']} / {row['prior']}"


def _pooled_stages(rows: list[dict]) -> dict[str, float | None]:
    """Per timing key, the median over rows of their per-row medians."""
    keys = dict.fromkeys(k for r in rows for k in r.get("stage_ms", {}))
    return {k: median((r["stage_ms"].get(k) for r in rows), digits=None) for k in keys}


def _peak_rss_mb() -> float:
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
