"""``orthonav bench real DATASET_DIR``: the localizer on real drone photos against a reference.

A dataset folder is laid out like ``../shared/data/real/seneca``: ``ortho.tif``, optional
``dsm.tif``, ``camera.json``, ``queries/`` (the photos) and ``queries.csv`` with the EXIF prior
(``lat``, ``lon``) and a photogrammetric reference (``ref_cam_lat/lon``, ``ref_centre_lat/lon``,
``ref_agl_m``, ``ref_heading_deg``, ``ref_roll_deg``, ``ref_pitch_deg``).

Fix sources run side by side: the keypoint localizer alone (per backend), the cascade (``fly``'s
default: correlation, keypoints, verification, a calibrated decision) and gradient correlation.

Priors are what a flight would give: the EXIF GPS position (sigma from the data), the heading,
height above ground and (in the ``+att`` variants) roll/pitch from the reference with seeded
noise of the stated size, as an autopilot would report them. Each variant (terrain model on or
off, attitude prior on or off) runs every photo; fixes are scored against the reference camera
position and the image centre on the ground.
"""

from __future__ import annotations

import csv
import itertools
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from orthonav.atomic import write_json_atomic
from orthonav.bench.machine import LoadWatch
from orthonav.bench.scoring import (
    CHI2_2DOF_95,
    COVERAGE_3SIGMA_TARGET,
    MEAN_NEES_TARGET,
    SIGMA_KEYS,
    SIGMA_OVER_P95_TARGET,
    error_enu_m,
    error_m,
    mean,
    mean_per_frame,
    median,
    nees,
    percentile,
    rate,
    share,
    sigma_coverage,
    sigma_targets,
    stage_tails,
    within_rates,
)
from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import backend_class
from orthonav.frames import load_frame
from orthonav.geo import GeoRaster, LocalFrame
from orthonav.localize import (
    CORRELATION,
    DEFAULT_COARSE_BACKBONE,
    FIX_SOURCES,
    KEYPOINTS,
    Fallback,
    LocalizerConfig,
    coarse_backbones,
    make_fix_source,
    parse_chain,
    warm_up,
)
from orthonav.mapdb import MapPackage, TilingConfig, attach_terrain, build_map, check_max_frame_px
from orthonav.types import Fix, FixSource, Prior, footprint_latlon
from orthonav.viz.real import plot_real_bench

FALSE_FIX_M = 10.0
WITHIN_M = (1.0, 2.0, 3.0, 5.0, 10.0)
SIGMA_TARGETS = (
    f">={COVERAGE_3SIGMA_TARGET:.0%} within 3 sigma, mean NEES <= {MEAN_NEES_TARGET:g}, "
    f"sigma <= {SIGMA_OVER_P95_TARGET:g}x p95 error"
)
REFERENCE_COLUMNS = ("name", "lat", "lon", "ref_cam_lat", "ref_cam_lon", "ref_centre_lat", "ref_centre_lon")
ATTITUDE_COLUMNS = ("ref_agl_m", "ref_heading_deg", "ref_roll_deg", "ref_pitch_deg")


@dataclass(frozen=True)
class RealBenchConfig:
    """What runs side by side, and the noise of the priors."""

    # A backend, or a fallback chain of them ("orb>aliked": ALIKED where ORB rejects the photo).
    features: tuple[str, ...] = ("orb",)
    fix_sources: tuple[str, ...] = (KEYPOINTS,)
    variants: tuple[str, ...] = ("flat", "flat+att", "dsm", "dsm+att")
    prior_sigma_m: float = 10.0
    heading_noise_deg: float = 3.0
    altitude_noise_m: float = 2.0
    attitude_noise_deg: float = 1.0
    attitude_sign: float = 1.0  # -1 flips roll and pitch: a wrongly configured autopilot
    limit: int | None = None  # the first N photos only (a quick look)
    seed: int = 0
    # The maps' frame size budget (map build --max-frame-px; None: each backend's own): a learned
    # extractor's cost follows it.
    max_frame_px: int | None = None
    # The cascade's coarse correlation (fly's --coarse-backbone).
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE

    def __post_init__(self) -> None:
        coarse_backbones(self.coarse_backbone)
        unknown = [v for v in self.variants if v.split("+")[0] not in ("flat", "dsm") or v.count("+") > 1]
        if unknown or any("+" in v and not v.endswith("+att") for v in self.variants):
            raise OrthonavError(f"bench real variants {unknown or self.variants}: expected flat|dsm[+att]")
        for features in self.features:
            parse_chain(features, "bench real features")
        check_max_frame_px(self.max_frame_px, "bench real max frame size (--max-frame-px)")
        if not self.fix_sources or set(self.fix_sources) - set(FIX_SOURCES):
            raise OrthonavError(
                f"bench real fix sources {list(self.fix_sources)}: expected some of {', '.join(FIX_SOURCES)}"
            )


@dataclass(frozen=True)
class Query:
    """One photo with its EXIF prior and its reference pose."""

    path: Path
    prior_lat: float
    prior_lon: float
    cam_lat: float
    cam_lon: float
    centre_lat: float
    centre_lon: float
    agl_m: float
    heading_deg: float
    roll_deg: float
    pitch_deg: float


@dataclass
class Outcome:
    """One photo's result in one variant."""

    name: str
    accepted: bool
    reference: tuple[float, float]  # the reference camera's lat, lon
    reason: str = ""
    position: tuple[float, float] | None = None  # the fix's lat, lon
    error_m: float | None = None
    centre_error_m: float | None = None
    sigma_m: float | None = None
    # The error's normalised squared size under the fix's own covariance (east, north): a
    # chi-square of 2 dof where the covariance is honest (mean 2, 95 % below 5.99).
    nees: float | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    # Fixed by the backend's descriptors alone (``LocalizerConfig.quick``), without its matcher.
    quick: bool = False
    # The camera position error of the pose found, accepted or not (None: no pose).
    placed_error_m: float | None = None


def read_queries(dataset: Path) -> list[Query]:
    """The photos of ``queries.csv`` that exist in ``queries/``, or a clear error."""
    table = dataset / "queries.csv"
    if not table.is_file():
        raise OrthonavError(f"{table}: missing (expected a queries.csv with EXIF and ref_* columns)")
    with table.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    missing = [c for c in (*REFERENCE_COLUMNS, *ATTITUDE_COLUMNS) if rows and c not in rows[0]]
    if not rows or missing:
        raise OrthonavError(f"{table}: expected columns {', '.join(missing) or 'and rows'}")
    queries = []
    for row in rows:
        path = dataset / "queries" / row["name"]
        if not path.is_file():
            raise OrthonavError(f"{table}: photo {row['name']} is not in {dataset / 'queries'}")
        try:
            values = {k: float(row[k]) for k in REFERENCE_COLUMNS[1:] + ATTITUDE_COLUMNS}
        except ValueError as exc:
            raise OrthonavError(f"{table}, {row['name']}: expected numbers ({exc})") from None
        queries.append(
            Query(
                path,
                values["lat"],
                values["lon"],
                values["ref_cam_lat"],
                values["ref_cam_lon"],
                values["ref_centre_lat"],
                values["ref_centre_lon"],
                values["ref_agl_m"],
                values["ref_heading_deg"],
                values["ref_roll_deg"],
                values["ref_pitch_deg"],
            )
        )
    return queries


def make_prior(query: Query, config: RealBenchConfig, attitude: bool, rng: np.random.Generator) -> Prior:
    """EXIF position; heading, height and (optionally) roll/pitch from the reference plus noise."""
    noise = rng.normal(size=4)
    roll = query.roll_deg + config.attitude_noise_deg * noise[2]
    pitch = query.pitch_deg + config.attitude_noise_deg * noise[3]
    return Prior(
        query.prior_lat,
        query.prior_lon,
        query.agl_m + config.altitude_noise_m * noise[0],
        query.heading_deg + config.heading_noise_deg * noise[1],
        config.attitude_sign * pitch if attitude else None,
        config.attitude_sign * roll if attitude else None,
        sigma_m=config.prior_sigma_m,
        heading_sigma_deg=max(config.heading_noise_deg, 1.0),
        attitude_sigma_deg=max(config.attitude_noise_deg, 0.1),
    )


def reference_footprint(camera: Camera, query: Query) -> np.ndarray:
    """(4, 2) lat, lon of the photo's corners on the ground from its reference pose (level
    ground at the reference height: a picture's outline, not a measurement)."""
    return footprint_latlon(
        camera, query.cam_lat, query.cam_lon, query.agl_m, query.heading_deg, query.pitch_deg, query.roll_deg
    )


def score(query: Query, fix: Fix) -> Outcome:
    """The fix against the reference camera position and image centre."""
    reference = (query.cam_lat, query.cam_lon)
    out = Outcome(query.path.name, fix.accepted, reference, fix.reason, timings_ms=dict(fix.timings_ms))
    if fix.pose is not None:
        out.placed_error_m = error_m(query.cam_lat, query.cam_lon, fix.pose.lat, fix.pose.lon)
    if fix.accepted:
        out.position = (fix.pose.lat, fix.pose.lon)
        out.error_m = out.placed_error_m
        out.centre_error_m = error_m(
            query.centre_lat, query.centre_lon, fix.pose.centre_lat, fix.pose.centre_lon
        )
        out.sigma_m = fix.sigma_m
        q = fix.quality  # the keypoints' own flag, or the cascade's where it took their pose
        out.quick = q.get("quick", q.get("fine_quick", 0.0) * q.get("fine_used", 0.0)) == 1.0
        local = LocalFrame.around(query.cam_lat, query.cam_lon)
        out.nees = nees(fix, error_enu_m(local, reference, out.position))
    return out


def metrics(outcomes: list[Outcome]) -> dict:
    """Rates over all photos; error statistics and sigma coverage over the accepted fixes."""
    n = len(outcomes)
    fixed = [o for o in outcomes if o.accepted]
    placed = [o for o in outcomes if o.placed_error_m is not None]
    e = np.array([o.error_m for o in fixed], float)
    c = np.array([o.centre_error_m for o in fixed], float)
    sigmas = [o.sigma_m for o in fixed]
    nees_values = np.array([o.nees for o in fixed if o.nees is not None], float)
    totals = [o.timings_ms["total_ms"] for o in outcomes if "total_ms" in o.timings_ms]

    def timing(key: str) -> float | None:
        return median(o.timings_ms[key] for o in outcomes if key in o.timings_ms)

    return {
        "n": n,
        "fixed": rate(len(fixed), n),
        **within_rates(e, n, WITHIN_M),
        # What a perfect decision on the poses found would fix (see bench localize's).
        "placed_within_3m": share((o.placed_error_m <= 3.0 for o in placed), n),
        "median_m": median(e, 2),
        "p90_m": percentile(e, 90, 2),
        "centre_median_m": median(c, 2),
        "false_fixes": int(np.sum(e > FALSE_FIX_M)),
        **sigma_coverage(list(e), sigmas, list(nees_values)),
        "median_sigma_m": median(sigmas, 2),
        "nees_below_chi2_95": mean(nees_values <= CHI2_2DOF_95, 2),
        # Every stage the fix source times (keypoints: extract, match, pose; the cascade: coarse,
        # fine, verify, ...), the median over the photos that reached it.
        **{key: timing(key) for key in dict.fromkeys(k for o in outcomes for k in o.timings_ms)},
        # A fallback chain's time is skewed (most photos the first source's, a few all of them'):
        # its mean is what a flight's duty cycle sees.
        "mean_total_ms": mean(totals),
        "mean_stage_ms": mean_per_frame([o.timings_ms for o in outcomes]),
        # The tails a companion schedules around: p50 / p95 / p99 / max of every stage.
        "tails_ms": stage_tails(
            [o.timings_ms for o in outcomes], dict.fromkeys(k for o in outcomes for k in o.timings_ms)
        ),
        # Photos fixed without the learned matcher (descriptors first): the rest of a learned
        # backend's fixes paid for LightGlue.
        "quick_fixes": share((o.quick for o in fixed), n),
    }


def tail_rows(result: dict) -> list[dict]:
    """One row per run and stage: the stage's p50 / p95 / p99 / max over the photos."""
    return [
        {"run": f"{r['features']} {r['fix_source']} {r['variant']}", "stage": stage, **tails}
        for r in result["rows"]
        for stage, tails in r.get("tails_ms", {}).items()
    ]


def run_real_benchmark(
    dataset: Path,
    out: Path,
    config: RealBenchConfig,
    progress: Callable[[str, int], None] | None = None,
) -> dict:
    """Every backend x variant over the dataset's photos; JSON (and the rows) returned and written.

    ``progress(what, total)`` is called after each photo, with the number of runs in all."""
    watch = LoadWatch()
    camera = Camera.from_json(dataset / "camera.json")
    every_query = read_queries(dataset)
    queries = every_query[: config.limit]
    dsm = dataset / "dsm.tif"
    if any(v.startswith("dsm") for v in config.variants) and not dsm.is_file():
        raise OrthonavError(f"{dsm}: missing; run the flat variants only (--variants flat,flat+att)")
    rows, per_photo = [], {}
    per_backend = len(set(config.fix_sources) - {CORRELATION})
    runs = len(config.features) * per_backend + (CORRELATION in config.fix_sources)
    total = runs * len(config.variants) * len(queries)
    maps = out.parent / f"{out.stem}_maps"
    with ExitStack() as stack:
        raster = stack.enter_context(GeoRaster(dataset / "ortho.tif"))  # read by correlation, warm-ups
        for features in config.features:
            chain = parse_chain(features, "bench real features")
            px = config.max_frame_px
            packages = [dataset_map(dataset, maps, camera, f, every_query, dsm, px) for f in chain]
            for fix_source, variant in itertools.product(config.fix_sources, config.variants):
                if fix_source == CORRELATION and features != config.features[0]:
                    continue  # the orthophoto's gradients: the same for every backend
                localizer = LocalizerConfig(use_terrain=variant.startswith("dsm"))
                sources = [
                    make_fix_source(
                        fix_source, p, camera, raster, localizer, coarse_backbone=config.coarse_backbone
                    )
                    for p in packages
                ]
                for each, package in zip(sources, packages, strict=True):  # timed as fly runs them
                    warm_up(each, raster, camera, package.tiling.nominal_alt_m)
                source = sources[0] if len(sources) == 1 else Fallback(sources, chain)
                row = {"features": features, "fix_source": fix_source, "variant": variant}
                what = f"{_label(row)} {variant}"
                outcomes = _run(source, queries, config, variant.endswith("+att"), progress, what, total)
                per_photo[what] = [asdict(o) for o in outcomes]
                rows.append({**row, **metrics(outcomes), "halves": split_coverage(outcomes)})
    result = {
        "dataset": str(dataset),
        "config": asdict(config),
        "photos": len(queries),
        "rows": rows,
        "per_photo": per_photo,
        "footprints": [reference_footprint(camera, q).round(7).tolist() for q in queries],
        "targets": _targets(rows),
        "machine": watch.record(),
    }
    write_json_atomic(out, result)
    plot_real_bench(result, dataset / "ortho.tif", out.with_suffix(".png"))
    return result


def _run(
    source: FixSource,
    queries: list[Query],
    config: RealBenchConfig,
    attitude: bool,
    progress: Callable[[str, int], None] | None,
    what: str,
    total: int,
) -> list[Outcome]:
    """Every photo through ``source`` with its prior (the same seeded noise for every variant)."""
    rng = np.random.default_rng(config.seed)
    outcomes = []
    for query in queries:
        prior = make_prior(query, config, attitude, rng)
        outcomes.append(score(query, source.localize(load_frame(query.path), prior)))
        if progress:
            progress(what, total)
    return outcomes


def dataset_map(
    dataset: Path,
    maps: Path,
    camera: Camera,
    features: str,
    queries: list[Query],
    dsm: Path,
    max_frame_px: int | None = None,
) -> MapPackage:
    """The dataset's map package for one backend and frame budget (None: the backend's own),
    built once under ``maps`` (reused when present, named by the budget) for the median height
    of all its photos: a run on the first few builds the map a full run does."""
    budget = backend_class(features).frame_budget_px if max_frame_px is None else max_frame_px
    where = maps / f"{features}_{budget}px"
    if (where / "manifest.json").is_file():
        package = MapPackage(where)
    else:
        tiling = TilingConfig(float(np.median([q.agl_m for q in queries])), max_frame_px=budget)
        package = build_map(dataset / "ortho.tif", where, camera, tiling, features, {})
    if dsm.is_file() and package.terrain is None:
        package = attach_terrain(package, dsm)
    return package


def split_coverage(outcomes: list[Outcome]) -> dict[str, dict]:
    """The sigma figures on each half of the photos (even and odd places in capture order): the
    flat-ground sigma was calibrated on the first half and is reported on the second."""
    halves = {"calibration": outcomes[0::2], "report": outcomes[1::2]}
    return {name: {k: metrics(half)[k] for k in SIGMA_KEYS} for name, half in halves.items() if half}


def _targets(rows: list[dict]) -> dict[str, bool | None]:
    """The real-photo targets, per backend and variant; the sigma's apart (None: no fixes)."""
    sigma = {f"{_label(r)} {r['variant']}: {SIGMA_TARGETS}": sigma_targets(r) for r in rows}
    return sigma | {
        f"{_label(r)} {r['variant']}: >=90% fixed, >=90% within 3 m, 0 false, >=90% within 3 sigma": (
            r["fixed"] >= 0.9
            and r["within_3m"] >= 0.9
            and r["false_fixes"] == 0
            and (r["within_3sigma"] or 0) >= 0.9
        )
        for r in rows
    }


def _label(row: dict) -> str:
    """A row's name: the backend (keypoints alone), the backend and cascade, or correlation (which
    uses no keypoints)."""
    source = row.get("fix_source", KEYPOINTS)
    if source == KEYPOINTS:
        return row["features"]
    return source if source == CORRELATION else f"{row['features']} {source}"
