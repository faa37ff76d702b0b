"""``orthonav models``: the learned models' files, exported for ONNX Runtime (no torch on the vehicle)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from orthonav.cli.output import console
from orthonav.errors import OrthonavError

models_app = typer.Typer(help="Learned models: export them for ONNX Runtime.", no_args_is_help=True)
EXPORTABLE_FEATURES = (
    "xfeat",
    "aliked",
    "aliked-n16rot",
    "disk",
    "lightglue-aliked",
    "lightglue-disk",
    "lightglue-xfeat",
)


@models_app.callback()
def _models() -> None:
    """Learned models: export them for ONNX Runtime (a group, so `orthonav models export` stays one)."""


@models_app.command("export")
def models_export(
    model: Annotated[
        Path | None,
        typer.Argument(
            help="Model file (.pt): a correction or retrieval model. Default: the shipped correction model."
        ),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(
            help="ONNX file to write (default: the cache, named by the model's sha256). MODEL.onnx "
            "beside MODEL.pt (MODEL.int8.onnx with --int8) is found at run time without naming it."
        ),
    ] = None,
    int8: Annotated[
        bool, typer.Option("--int8", help="Static int8 quantisation (needs --calibration).")
    ] = False,
    calibration: Annotated[
        list[Path] | None,
        typer.Option(help="Orthophoto(s) (GeoTIFF) whose crops calibrate int8's ranges; repeatable."),
    ] = None,
    crops: Annotated[int, typer.Option(help="Calibration crops.")] = 32,
    features: Annotated[
        str | None,
        typer.Option(
            help="Export a keypoint network instead of a model file (from the weights its package "
            "ships): xfeat (xfeat-mnn's network on a CPU), aliked, aliked-n16rot or disk (their extractor "
            "on a CPU, any keypoint count). fp32; ALIKED's also int8. xfeat's and aliked's graphs ship "
            "with orthonav (aliked's in both). lightglue-aliked, lightglue-disk, lightglue-xfeat: the "
            "LightGlue of those features (LighterGlue for xfeat), one folder of graphs, into the cache "
            "(or --out DIR): what matches them where torch is not installed; copy the folder into that "
            "machine's cache."
        ),
    ] = None,
    force: Annotated[bool, typer.Option(help="Export even if the file is up to date.")] = False,
) -> None:
    """Export a model file or a keypoint network to ONNX (dynamic image size), checked by the
    weights' sha256 at run time."""
    try:
        from orthonav.models.export import calibration_crops, export_onnx
        from orthonav.models.export_features import export_aliked_onnx, export_disk_onnx, export_xfeat_onnx
    except ImportError as exc:
        raise OrthonavError(
            f"exporting needs torch, onnx and onnxscript ({exc.name} is missing): "
            "pip install 'orthonav[learned]'"
        ) from None
    from orthonav.models import shipped_model_path

    for path in calibration or []:
        if not path.is_file():
            raise OrthonavError(f"{path}: no such calibration orthophoto")
    images = calibration_crops(calibration, crops) if int8 and calibration else None
    if features is not None:
        if features not in EXPORTABLE_FEATURES:
            raise OrthonavError(f"--features {features!r}: expected one of {', '.join(EXPORTABLE_FEATURES)}")
        if model is not None:
            raise OrthonavError("give either a model file or --features, not both")
        started = time.time()
        precision = "int8" if int8 else "fp32"
        if features.startswith("lightglue-"):
            if int8:
                raise OrthonavError(f"--features {features}: LightGlue is exported in fp32 only")
            from orthonav.models.export_glue import export_lightglue_onnx

            written = export_lightglue_onnx(features.removeprefix("lightglue-"), out=out, force=force)
        elif features == "xfeat":
            written = export_xfeat_onnx(precision=precision, out=out, force=force)
        elif features == "disk":
            from orthonav.models.onnx.files import disk_weights_path

            written = export_disk_onnx(disk_weights_path(), precision, out=out, force=force)
        else:
            from orthonav.features import backend_class
            from orthonav.models.onnx.files import aliked_weights_path

            # The backend's name is not its weights' (aliked: aliked-n16).
            weights = aliked_weights_path(backend_class(features, "onnx").model_name)
            written = export_aliked_onnx(weights, precision, out=out, force=force, calibration=images)
        console.print(f"{features} -> {written}: {_done(written, started)}")
        return
    model = model or shipped_model_path()
    started = time.time()
    written = export_onnx(model, "int8" if int8 else "fp32", out=out, calibration=images, force=force)
    console.print(f"{model.name} -> {written}: {_done(written, started)}")


def _done(written: Path, started: float) -> str:
    return "exported" if written.stat().st_mtime >= started - 1.0 else "up to date (--force re-exports)"
