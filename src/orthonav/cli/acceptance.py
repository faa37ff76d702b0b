"""``orthonav bench acceptance``: fit the cascade's acceptance model, reproducibly."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from orthonav.cli.inputs import SHARED_DATA
from orthonav.cli.output import console, print_rows
from orthonav.errors import OrthonavError

# The collection settings when not given (the library's config has 40 frames a pair).
CLI_DEFAULTS = {
    "frames": 50,
    "same_date_frames": 20,
    "seed": 1,
    "features": "orb",
    "coarse_backbone": "gradient",
}


def bench_acceptance(
    data: Annotated[Path, typer.Option(help="Folder of co-registered GeoTIFFs of one area (dates).")] = (
        SHARED_DATA / "naip"
    ),
    frames: Annotated[
        int | None,
        typer.Option(
            help=f"Frames per ordered pair of different dates.  [default: {CLI_DEFAULTS['frames']}]"
        ),
    ] = None,
    same_date_frames: Annotated[
        int | None,
        typer.Option(
            help=f"Frames per date against its own map.  [default: {CLI_DEFAULTS['same_date_frames']}]"
        ),
    ] = None,
    seed: Annotated[
        int | None,
        typer.Option(help=f"Random seed (bench localize renders with 0).  [default: {CLI_DEFAULTS['seed']}]"),
    ] = None,
    features: Annotated[
        str | None,
        typer.Option(
            help=f"Keypoint backend of the maps (the fine stage).  [default: {CLI_DEFAULTS['features']}]"
        ),
    ] = None,
    years: Annotated[
        str | None, typer.Option(help="Only the files whose names contain one of these, comma-separated.")
    ] = None,
    trunk: Annotated[
        bool,
        typer.Option(
            help="Measure how well the features of orthonav's trained CNN agree between frame and map at "
            "each pose and fit a model that uses it (shipped as acceptance_naip_<backend>_trunk.json; it "
            "needs torch or ONNX Runtime to run the CNN)."
        ),
    ] = False,
    coarse_backbone: Annotated[
        str | None,
        typer.Option(
            help="The cascade's coarse correlation whose evidence is collected: gradient, orientation "
            "(its models ship as acceptance_naip[_aliked]_orientation[_trunk].json) or trained (with "
            "--trunk, ALIKED's ships as acceptance_naip_aliked_trained_trunk.json).  "
            f"[default: {CLI_DEFAULTS['coarse_backbone']}]"
        ),
    ] = None,
    without: Annotated[
        str | None,
        typer.Option(
            help="Evidence left out of the model, comma-separated feature names (ORB's shipped "
            "models with the trunk, and ALIKED's after the gradient correlation, leave out "
            "trunk_relative_margin)."
        ),
    ] = None,
    refit: Annotated[
        bool,
        typer.Option(
            help="Refit from the records written by an earlier run (no frames run), with the frames, "
            "seed, features and correlation they were collected with (others given are refused)."
        ),
    ] = False,
    records: Annotated[
        Path | None, typer.Option(help="The per-frame records JSON (default: beside --out).")
    ] = None,
    score: Annotated[
        Path | None,
        typer.Option(
            help="Score this model JSON (e.g. the shipped models/weights/acceptance_naip.json) on the "
            "records instead of fitting one: is it calibrated for this backend's evidence?"
        ),
    ] = None,
    out: Annotated[
        Path, typer.Option(help="Model JSON (the per-frame records are written beside it).")
    ] = Path("runs/acceptance_naip.json"),
) -> None:
    """Fit the cascade's acceptance model on cross-date frames at known poses (west half of the
    area), score it on the east half; copy the JSON to models/weights/ to ship it. With --score,
    an existing model is scored on the frames instead."""
    from orthonav.bench.acceptance import AcceptanceFitConfig, reliability_png, run_acceptance_fit

    sources = sorted(data.glob("*.tif"))
    if years:
        wanted = [y.strip() for y in years.split(",") if y.strip()]
        sources = [p for p in sources if any(y in p.name for y in wanted)]
    if len(sources) < 2 and not refit:
        raise OrthonavError(f"{data}: needs GeoTIFFs of at least two dates (got {len(sources)})")
    model_features = _model_features(trunk, without)
    given = {
        "frames": frames,
        "same_date_frames": same_date_frames,
        "seed": seed,
        "features": features,
        "coarse_backbone": coarse_backbone,
    }
    asked = {key: value for key, value in given.items() if value is not None}
    config = AcceptanceFitConfig(**{**CLI_DEFAULTS, **asked}, model_features=model_features)
    model = run_acceptance_fit(
        sources, out, config, records, reuse_records=refit, score_model=score, asked=tuple(asked)
    )
    rows = [
        {"half": half, "condition": condition, **scores}
        for half, by_condition in model["scores"].items()
        for condition, scores in by_condition.items()
    ]
    fitted = f"scored: {model['scored_model']}" if "scored_model" in model else "fitted on the west half"
    print_rows(f"acceptance at P >= {model['threshold']:.3f} ({fitted})", rows)
    weights = [
        {"feature": f, "coefficient": c} for f, c in zip(model["features"], model["coef"], strict=True)
    ]
    print_rows("coefficients (per standard deviation of each feature)", weights)
    calibration = model["calibration"]
    bins = calibration["bins"]
    print_rows(f"calibration: {calibration['of']}, equal-count bins of P(right)", bins)
    met = sum(row["within"] for row in bins)
    tolerance = round(100 * calibration["tolerance"])
    console.print(
        f"calibration: {met} of {len(bins)} bins within {tolerance} points "
        f"({'target met' if calibration['within_tolerance'] else 'target missed'}); "
        f"reliability diagram {reliability_png(out)}"
    )
    console.print(f"written {out}")


def _model_features(trunk: bool, without: str | None) -> tuple[str, ...]:
    """The evidence the model weighs: the base (and the trunk's) less the names in ``without``."""
    from orthonav.localize.acceptance import BASE_FEATURES, TRUNK_FEATURES

    available = (*BASE_FEATURES, *TRUNK_FEATURES) if trunk else BASE_FEATURES
    dropped = {name.strip() for name in (without or "").split(",") if name.strip()}
    unknown = sorted(dropped - set(available))
    if unknown:
        raise OrthonavError(
            f"--without: {unknown} is not evidence of this model; expected names from {', '.join(available)}"
        )
    return tuple(name for name in available if name not in dropped)
