"""Fitting the cascade's acceptance model on real cross-date imagery, reproducibly.

Data: for each ordered pair of dates of a folder of co-registered orthophotos (NAIP years), a
map package of one date and frames rendered from the other at random known poses, as
``orthonav bench localize`` renders them (1000 m, 640x480, 60 deg, tilt up to 5 deg, a prior
within 200 m and 10 deg, baro altitude and AHRS roll/pitch with their noise), but from another
seed, so the benchmark's frames are not the fit's; a few frames of each date against its own
map too (same-date: what strong keypoint evidence looks like). Each frame runs through the
cascade up to the decision (:meth:`Cascade.propose`); its evidence and true errors are recorded.

Fit: a frame is right when the pose's point under the drone is within ``false_m`` of the truth.
The area is split in two by longitude: the logistic regression is fitted on the western half
(by the true image centre) and scored on the eastern half, which it never saw (a frame's
footprint may straddle the line: the halves share no frame, but a little ground near it). The
threshold is the lowest probability at which the western half's cross-date false fixes stay
within ``target_false_rate x margin`` of its cross-date frames. Model, data description and the scores on both
halves are written as one small JSON; the per-frame records beside it allow refitting alone.

Calibration: on the eastern half, the fixes the model accepts are sorted by their P(right) and
split into equal-count bins (deciles; fewer bins when there are few fixes); each bin's mean P is
set against the share of its poses that were right, within 5 points or not (the issue's target),
in the JSON, and drawn as a reliability diagram beside it.
"""

from __future__ import annotations

import json
import platform
import tempfile
from collections.abc import Collection
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from orthonav.atomic import sha256_file, write_json_atomic
from orthonav.bench.calibration import calibration_table
from orthonav.bench.localize import LocalizeBenchConfig, Sample, render_samples
from orthonav.bench.scoring import error_m, share
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.localize.acceptance import (
    BASE_FEATURES,
    FEATURES,
    TRUNK_FEATURES,
    AcceptanceModel,
    feature_vector,
    fit_logistic,
)
from orthonav.localize.cascade import Cascade, cascade_config
from orthonav.localize.dense import BACKBONES, GRADIENT
from orthonav.mapdb import TilingConfig, build_map
from orthonav.models import shipped_model_path
from orthonav.viz.calibration import plot_reliability

FIT_HALF, TEST_HALF = "west", "east"
# The settings that decide which frames are run: reused records keep theirs.
COLLECTION_SETTINGS = ("frames", "same_date_frames", "seed", "features", "coarse_backbone")
CROSS, SAME = "cross-date", "same-date"


@dataclass(frozen=True)
class AcceptanceFitConfig:
    """Everything that decides the model; written into it."""

    frames: int = 40  # per ordered pair of dates
    same_date_frames: int = 20  # per date against its own map
    seed: int = 1  # bench localize renders with seed 0: other frames
    features: str = "orb"  # the keypoint stage's backend (the maps' features)
    # The coarse stage's correlation (CorrectionConfig.backbone): gradient, or trained.
    coarse_backbone: str = GRADIENT
    false_m: float = 25.0
    target_false_rate: float = 0.005
    # The threshold keeps the fitted half's false fixes within target x margin (small samples).
    margin: float = 0.5
    l2: float = 1.0
    # The base evidence; with TRUNK_FEATURES too, the frames are collected with the trained
    # trunk's agreement measured (Verifier.trunk_agreement) and the model needs the trunk.
    model_features: tuple[str, ...] = BASE_FEATURES

    def __post_init__(self) -> None:
        unknown = set(self.model_features) - set(FEATURES)
        if (
            self.frames < 1
            or self.same_date_frames < 0
            or unknown
            or not 0 < self.target_false_rate < 1
            or not 0 < self.margin <= 1
        ):
            raise OrthonavError(
                f"acceptance fit: expected frames >= 1, 0 < target < 1, 0 < margin <= 1 and features "
                f"from {', '.join(FEATURES)} (unknown: {sorted(unknown)})"
            )
        if self.coarse_backbone not in BACKBONES:
            raise OrthonavError(
                f"acceptance fit: coarse backbone {self.coarse_backbone!r}: expected one of "
                f"{', '.join(BACKBONES)}"
            )


def collect_records(
    sources: list[Path], config: AcceptanceFitConfig, progress: bool = True, workdir: Path | None = None
) -> list[dict]:
    """Per frame of every ordered pair of dates: the cascade's evidence and the true errors."""
    if len(sources) < 2:
        raise OrthonavError(f"acceptance fit: needs at least two dates of one area, got {len(sources)}")
    bench = LocalizeBenchConfig(frames=config.frames, seed=config.seed, features=(config.features,))
    camera = bench.camera
    band = (bench.alt_m, bench.alt_m)
    samples = {p: render_samples(p, camera, band, bench) for p in sources}
    records: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="orthonav-acceptance-", dir=workdir) as tmp:
        for map_path in sources:
            tiling = TilingConfig(nominal_alt_m=bench.alt_m)
            out = Path(tmp) / map_path.stem
            package = build_map(map_path, out, camera, tiling, config.features, progress=False)
            with GeoRaster(map_path) as raster:
                # The fit's correlation; the trunk measured on every proposal where it is weighed,
                # the blocks on every one (the model to fit decides whether it weighs them).
                checks = cascade_config(config.coarse_backbone, _uses_trunk(config))
                checks = replace(checks, blocks_check=True)
                cascade = Cascade(package, raster, camera, checks)
                split_lon = float(raster.pixel_to_latlon(raster.width / 2.0, raster.height / 2.0)[1])
                for frames_path in sources:
                    same = frames_path == map_path
                    chosen = samples[frames_path][: config.same_date_frames] if same else samples[frames_path]
                    desc = f"acceptance {map_path.stem[-8:]} <- {frames_path.stem[-8:]}"
                    for i, sample in enumerate(tqdm(chosen, desc=desc, disable=not progress)):
                        record = _record(cascade, sample, split_lon)
                        condition = SAME if same else CROSS
                        pair = {"map": map_path.stem, "frames": frames_path.stem, "condition": condition}
                        records.append({**pair, "i": i, **record})
    return records


def _record(cascade: Cascade, sample: Sample, split_lon: float) -> dict:
    fix = cascade.propose(sample.frame, sample.prior)
    half = FIT_HALF if sample.centre[1] < split_lon else TEST_HALF
    out = {"half": half, "pose": fix.pose is not None, "reason": fix.reason}
    out["quality"] = {k: round(float(v), 5) for k, v in fix.quality.items()}
    out["timings_ms"] = {k: round(float(v), 2) for k, v in fix.timings_ms.items()}
    if fix.pose is not None:
        truth = sample.truth
        out["error_m"] = round(error_m(truth.lat, truth.lon, fix.pose.lat, fix.pose.lon), 3)
        out["centre_error_m"] = round(error_m(*sample.centre, fix.pose.centre_lat, fix.pose.centre_lon), 3)
        out["sigma_m"] = round(float(fix.sigma_m), 3)
    return out


def fit_acceptance(records: list[dict], config: AcceptanceFitConfig, data: dict) -> dict:
    """The model JSON (coefficients, threshold, data description, scores on both halves)."""
    halves = _halves(records)
    x, y = _design(halves[FIT_HALF], config)
    mean, scale, coef, intercept = fit_logistic(x, y, config.l2)
    model = AcceptanceModel(config.model_features, mean, scale, coef, intercept, 0.5)
    threshold = _threshold(model, _of(halves[FIT_HALF], CROSS), config)
    model = AcceptanceModel(config.model_features, mean, scale, coef, intercept, threshold)
    info = {
        "fitted_on": f"{FIT_HALF} half of the area",
        "label": f"right: the point under the drone within {config.false_m:g} m of the truth",
        "threshold_rule": (
            f"lowest P at which the {FIT_HALF} half's cross-date false fixes (> {config.false_m:g} m) "
            f"stay within {config.target_false_rate * config.margin:.4f} of its cross-date frames"
        ),
        "data": data,
        "config": asdict(config),
        **_evaluation(model, halves, config),
    }
    return AcceptanceModel(config.model_features, mean, scale, coef, intercept, threshold, info).to_dict()


def score_acceptance(
    records: list[dict], model: AcceptanceModel, config: AcceptanceFitConfig, data: dict, source: str
) -> dict:
    """An existing model (e.g. the shipped one, fitted on another backend's evidence) scored on
    these records as a fitted one is: rates on both halves at its own threshold, calibration
    on the held-out half. The model JSON with these scores in place of its own."""
    config = replace(config, model_features=model.features)
    scored = {**model.to_dict(), "scored_model": source, "data": data, "config": asdict(config)}
    return scored | _evaluation(model, _halves(records), config)


def _halves(records: list[dict]) -> dict[str, list[dict]]:
    return {half: [r for r in records if r["half"] == half] for half in (FIT_HALF, TEST_HALF)}


def _evaluation(model: AcceptanceModel, halves: dict[str, list[dict]], config: AcceptanceFitConfig) -> dict:
    """Scores per half and condition, and the calibration of the accepted held-out fixes."""
    scores = {
        half: {c: _scores(model, _of(rows, c), config) for c in (CROSS, SAME) if _of(rows, c)}
        for half, rows in halves.items()
    }
    x, y = _design(halves[TEST_HALF], config)
    p = model.probabilities(x) if len(x) else np.zeros(0)
    accepted = p >= model.threshold
    return {
        "scores": scores,
        "calibration": {
            "of": f"the fixes accepted on the {TEST_HALF} half (held out), both conditions",
            **calibration_table(p[accepted], y[accepted]),
        },
    }


def _of(rows: list[dict], condition: str) -> list[dict]:
    return [r for r in rows if r.get("condition", CROSS) == condition]


def _design(rows: list[dict], config: AcceptanceFitConfig) -> tuple[np.ndarray, np.ndarray]:
    posed = [r for r in rows if r["pose"]]
    x = np.array([feature_vector(r["quality"], config.model_features) for r in posed])
    y = np.array([r["error_m"] <= config.false_m for r in posed], dtype=float)
    return x, y


def _threshold(model: AcceptanceModel, rows: list[dict], config: AcceptanceFitConfig) -> float:
    """The lowest threshold meeting the false-fix budget on ``rows`` (every posed frame's P tried)."""
    x, y = _design(rows, config)
    p = model.probabilities(x)
    budget = config.target_false_rate * config.margin * len(rows)
    candidates = np.unique(np.concatenate([p, [0.5]]))
    for t in candidates[candidates >= 0.5]:
        if float(np.sum((p >= t) & (y == 0))) <= budget:
            return float(min(t, 0.999))
    return 0.999


def _scores(model: AcceptanceModel, rows: list[dict], config: AcceptanceFitConfig) -> dict:
    """Rates over every frame of ``rows`` at the model's threshold, and how well P ranks."""
    n = len(rows)
    posed = [r for r in rows if r["pose"]]
    x, y = _design(rows, config)
    p = model.probabilities(x) if len(x) else np.zeros(0)
    accepted = p >= model.threshold
    errors = np.array([r["error_m"] for r in posed])
    right = y == 1
    return {
        "frames": n,
        "posed": len(posed),
        "right_poses": int(right.sum()),
        "fixed": share(accepted, n, 4),
        "fixed_right": share(accepted & right, n, 4),
        "false_25m": share(accepted & (errors > 25.0), n, 4),
        "false_50m": share(accepted & (errors > 50.0), n, 4),
        "false_fixes": int((accepted & ~right).sum()),
        "auc": _auc(p, y),
        "log_loss": round(float(-np.mean(y * np.log(p + 1e-12) + (1 - y) * np.log(1 - p + 1e-12))), 4),
    }


def _auc(p: np.ndarray, y: np.ndarray) -> float | None:
    """Probability that a right pose scores above a wrong one (ties count half)."""
    pos, neg = p[y == 1], p[y == 0]
    if not len(pos) or not len(neg):
        return None
    greater = (pos[:, None] > neg[None, :]).mean() + 0.5 * (pos[:, None] == neg[None, :]).mean()
    return round(float(greater), 4)


def run_acceptance_fit(
    sources: list[Path],
    out_json: Path,
    config: AcceptanceFitConfig,
    records_json: Path | None = None,
    reuse_records: bool = False,
    progress: bool = True,
    score_model: Path | None = None,
    asked: Collection[str] = (),
) -> dict:
    """Collect (or reuse) the records, fit (or score ``score_model`` on them), write the model
    JSON (and the records beside it). Reused records keep the settings they were collected
    with; ``asked`` names the settings the caller chose, refused where the records disagree."""
    records_json = records_json or out_json.with_name(out_json.stem + "_records.json")
    if reuse_records:
        records, collected = _stored_records(records_json)
        for key in sorted(set(asked) & set(collected)):
            if collected[key] != getattr(config, key):
                raise OrthonavError(
                    f"{records_json}: the records were collected with {key}={collected[key]!r}, "
                    f"not {getattr(config, key)!r}; collect them again (without --refit) for that"
                )
        config = replace(config, **collected)  # the data is as it was collected
    else:
        records = collect_records(sources, config, progress)
        write_json_atomic(records_json, {"config": asdict(config), "records": records})
    data = _describe(sources, records, config)
    if _uses_trunk(config) and not any("trunk_margin" in r["quality"] for r in records if r["pose"]):
        raise OrthonavError(
            f"{records_json}: the records were collected without the trunk's agreement; collect them "
            "again with it (without --refit) to fit a model that uses it"
        )
    if score_model is None:
        model = fit_acceptance(records, config, data)
    else:
        model = score_acceptance(records, AcceptanceModel.load(score_model), config, data, str(score_model))
    write_json_atomic(out_json, model)
    title = f"{out_json.name}: calibration on the {TEST_HALF} half (held out)"
    plot_reliability(model["calibration"], reliability_png(out_json), title)
    return model


def _stored_records(records_json: Path) -> tuple[list[dict], dict[str, Any]]:
    """The records of an earlier run and the settings they were collected with."""
    try:
        stored = json.loads(records_json.read_text())
        # Records from before the choice of correlation were all collected with gradient.
        settings = {"coarse_backbone": GRADIENT, **stored["config"]}
        return stored["records"], {k: settings[k] for k in COLLECTION_SETTINGS}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise OrthonavError(f"{records_json}: cannot reuse the records ({exc!r})") from None


def _uses_trunk(config: AcceptanceFitConfig) -> bool:
    return any(name in TRUNK_FEATURES for name in config.model_features)


def reliability_png(out_json: Path) -> Path:
    """Where the reliability diagram of a model JSON goes: beside it."""
    return out_json.with_name(out_json.stem + "_reliability.png")


def _describe(sources: list[Path], records: list[dict], config: AcceptanceFitConfig) -> dict:
    pairs = sorted({(r["map"], r["frames"]) for r in records})
    return {
        "sources": [p.name for p in sources],
        "pairs": len(pairs),
        "frames_per_pair": config.frames,
        "same_date_frames_per_date": config.same_date_frames,
        "per_condition": {c: len(_of(records, c)) for c in (CROSS, SAME)},
        "frames": len(records),
        "per_half": {h: sum(r["half"] == h for r in records) for h in (FIT_HALF, TEST_HALF)},
        "frames_rendered": (
            "1000 m AGL (+-20 %), 640x480 px, 60 deg hfov, tilt up to 5 deg, photometric change 1.0; "
            "prior within 200 m (sigma 100 m) and 10 deg (sigma 5 deg), baro +-5 %, "
            "AHRS roll/pitch 0.3 deg noise (as orthonav bench localize, another seed)"
        ),
        "keypoint_backend": config.features,
        **({"trunk": _trunk_described()} if _uses_trunk(config) else {}),
        "python": platform.python_version(),
    }


def _trunk_described() -> dict:
    """Which trunk measured the agreement a model weighs: another trunk's scores differ."""
    path = shipped_model_path()
    return {"model": path.name, "sha256": sha256_file(path)}
