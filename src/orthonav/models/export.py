"""Export a model file (.pt) to an ONNX graph, fp32 or int8, for :mod:`orthonav.models.onnx`.

Needs torch, onnx and onnxscript (the learned extra); the file it writes runs with onnxruntime
alone. Height and width are dynamic (any view size), so one file serves every correction size.
The source model's sha256 goes into the graph's metadata: an up-to-date file is reused, a stale
one re-made, and the runtime refuses a file of another model. Files are written atomically.

int8 is static quantisation (QDQ, per-channel int8 weights, uint8 activations whose ranges
are calibrated on imagery the caller gives): the convolutions then run on the CPU's integer
units. Dynamic quantisation is no use here: onnxruntime's ConvInteger runs slower than fp32 on a CPU.
Nothing is downloaded.
"""

from __future__ import annotations

import contextlib
import io
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import onnx
import torch
from torch import nn

from orthonav.atomic import atomic_path, sha256_file
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.models.onnx.files import (
    CORRECTION,
    RETRIEVAL,
    OnnxRecord,
    cached_onnx_path,
    check_precision,
    open_session,
)
from orthonav.models.onnx.preprocess import VALID_CELL_FRACTION, standardise
from orthonav.models.retrieval import MODEL_FORMAT as RETRIEVAL_FORMAT
from orthonav.models.retrieval import RetrievalNet, load_retrieval_model
from orthonav.models.trunks import DenseFeatures, load_model

OPSET = 18
# Views of a 224 and a 448 px correction (frame 4:3, region 1.5x): what calibration should see.
CALIBRATION_SIZES = ((168, 224), (252, 336), (336, 448), (504, 672))


def export_onnx(
    model_path: str | Path,
    precision: str = "fp32",
    out: str | Path | None = None,
    cache_dir: str | Path | None = None,
    calibration: Sequence[np.ndarray] | None = None,
    force: bool = False,
) -> Path:
    """Write the ONNX graph of a correction or retrieval model file; returns its path.

    ``out`` defaults to the cache (named by the model's sha256). A file already there that was
    exported from this very model at this precision is kept unless ``force``. ``calibration``:
    RGB uint8 images (any sizes) for int8's activation ranges, e.g. :func:`calibration_crops`.
    """
    check_precision(precision)
    model_path = Path(model_path)
    if not model_path.is_file():
        raise OrthonavError(f"{model_path}: no such model file")
    sha = sha256_file(model_path)
    out = Path(out) if out else cached_onnx_path(sha, precision, cache_dir)
    if not force and _is_current(out, sha, precision):
        return out
    if precision == "int8" and not calibration:
        raise OrthonavError("an int8 export needs calibration imagery (e.g. --calibration ORTHO.tif)")
    kind, graph, trunk, info = _load(model_path)
    proto = _to_onnx(graph, kind)
    if precision == "int8":
        proto = quantize_int8(proto, [_feed(kind, rgb) for rgb in calibration])
    record = OnnxRecord(
        kind, sha, model_path.name, precision, trunk.backbone, trunk.stage, trunk.stride, info
    )
    write_onnx(proto, record, out)
    return out


def _is_current(path: Path, sha: str, precision: str) -> bool:
    if not path.is_file():
        return False
    try:
        _, record = open_session(path, threads=1)
    except OrthonavError:
        return False
    return record.source_sha256 == sha and record.precision == precision


# --- models as graphs -------------------------------------------------------------------------


class RetrievalGraph(nn.Module):
    """Image and its pixel mask -> (descriptor, number of valid cells): the valid cells are found
    in the graph, at the features' size, so the runtime needs no knowledge of the trunk's strides."""

    def __init__(self, net: RetrievalNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.net.trunk(image)
        cells = cell_means(mask, features.shape[2], features.shape[3])
        valid = (cells > VALID_CELL_FRACTION).float()
        return self.net.pool(features, valid), valid.flatten(1).sum(1)


def cell_means(mask: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    """Mean of a (B, 1, H, W) mask over rows x cols cells with adaptive average pooling's bounds,
    from an integral image: it exports with dynamic sizes, where ``F.adaptive_avg_pool2d`` bakes
    the example's cell bounds into the graph."""
    integral = torch.nn.functional.pad(mask.cumsum(2).cumsum(3), (1, 0, 1, 0))
    r0, r1 = _bounds(mask.shape[2], rows)
    c0, c1 = _bounds(mask.shape[3], cols)

    def at(r: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        return integral[:, :, r][:, :, :, c]

    sums = at(r1, c1) - at(r0, c1) - at(r1, c0) + at(r0, c0)
    return sums / ((r1 - r0)[:, None] * (c1 - c0)[None, :]).float()


def _bounds(size: int, cells: int) -> tuple[torch.Tensor, torch.Tensor]:
    i = torch.arange(cells)
    return i * size // cells, ((i + 1) * size + cells - 1) // cells


def _load(model_path: Path) -> tuple[str, nn.Module, DenseFeatures, dict]:
    """(kind, module to export, its trunk, recorded info) of a model file of either kind."""
    if _format_of(model_path) == RETRIEVAL_FORMAT:
        net, info = load_retrieval_model(model_path)
        return RETRIEVAL, RetrievalGraph(net).eval(), net.trunk, info
    trunk, info = load_model(model_path)  # any other file gets the correction model's clear errors
    return CORRECTION, trunk, trunk, info


def _format_of(path: Path) -> str | None:
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # unreadable: load_model says so
        return None
    return payload.get("format") if isinstance(payload, dict) else None


def _to_onnx(graph: nn.Module, kind: str) -> onnx.ModelProto:
    """The trunk (dynamic batch, height and width) or the retrieval graph (dynamic height and width)."""
    height, width = torch.export.Dim("height", min=16, max=8192), torch.export.Dim("width", min=16, max=8192)
    spatial = {2: height, 3: width}
    if kind == CORRECTION:
        args = (torch.zeros(1, 3, 168, 224),)
        shapes: tuple = ({0: torch.export.Dim("batch", min=1, max=1024), **spatial},)
        return trace_to_onnx(graph, args, shapes, ["image"], ["features"])
    args = (torch.zeros(1, 3, 168, 224), torch.ones(1, 1, 168, 224))
    return trace_to_onnx(graph, args, (spatial, spatial), ["image", "mask"], ["descriptor", "cells"])


def trace_to_onnx(
    graph: nn.Module,
    args: tuple[torch.Tensor, ...],
    dynamic_shapes: tuple,
    input_names: list[str],
    output_names: list[str],
    opset: int = OPSET,
) -> onnx.ModelProto:
    """torch.export -> ONNX (opset 18 unless told, optimised) with the given dynamic dimensions."""
    # The exporter reports its steps on stdout and warns about the shared height/width names.
    with torch.inference_mode(False), contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
        warnings.filterwarnings("ignore", ".*axis name", UserWarning)
        program = torch.onnx.export(
            graph,
            args,
            None,
            input_names=input_names,
            output_names=output_names,
            dynamic_shapes=dynamic_shapes,
            opset_version=opset,
            dynamo=True,
            optimize=True,
            verbose=False,
        )
    return program.model_proto


# --- int8 -------------------------------------------------------------------------------------


def _feed(kind: str, rgb: np.ndarray) -> dict[str, np.ndarray]:
    """A calibration image as the graph's inputs, prepared as the runtime prepares a view."""
    if kind == CORRECTION:
        return {"image": standardise(rgb)[None]}
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    image = standardise(np.repeat(gray[:, :, None], 3, axis=2))[None]
    return {"image": image, "mask": np.ones((1, 1, *gray.shape), np.float32)}


def quantize_int8(proto: onnx.ModelProto, feeds: list[dict[str, np.ndarray]]) -> onnx.ModelProto:
    """Static QDQ int8 (per channel, ranges from ``feeds``: the graph's inputs for calibration
    images). A trunk's convolutions, pooling and residual sums; its normalisation, the retrieval
    head and its valid-cell sums stay fp32 (int8 sums of the mask's integral image broke the
    descriptors: cosine 0.4 to fp32). A graph without the exporter's module scopes (ALIKED's,
    traced by TorchScript): its convolutions only (a ``DeformConv`` stays fp32)."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.feeds = iter(feeds)

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self.feeds, None)

    with tempfile.TemporaryDirectory(prefix="orthonav-int8-") as tmp:
        src, pre, dst = (Path(tmp) / name for name in ("fp32.onnx", "pre.onnx", "int8.onnx"))
        onnx.save_model(proto, src)
        quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
        quantize_static(
            str(pre),
            str(dst),
            Reader(),
            quant_format=QuantFormat.QDQ,
            per_channel=True,
            activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8,
            **_what_to_quantize(proto),
        )
        return onnx.load(str(dst))


def _what_to_quantize(proto: onnx.ModelProto) -> dict:
    """The trunk's nodes, by the module scopes the exporter records; only the convolutions
    where a graph has no such record."""
    trunk = [node.name for node in proto.graph.node if _in_trunk(node)]
    if not trunk:
        return {"op_types_to_quantize": ["Conv"]}
    return {"op_types_to_quantize": ["Conv", "MaxPool", "Add", "Relu"], "nodes_to_quantize": trunk}


def _in_trunk(node: onnx.NodeProto) -> bool:
    scopes = next((p.value for p in node.metadata_props if p.key == "pkg.torch.onnx.name_scopes"), "")
    return "'trunk'" in scopes or "'net.trunk'" in scopes


def calibration_crops(
    orthos: Sequence[str | Path],
    count: int = 32,
    sizes: Sequence[tuple[int, int]] = CALIBRATION_SIZES,
    seed: int = 0,
) -> list[np.ndarray]:
    """``count`` random RGB crops (view-sized, at the orthophotos' resolution) of ``orthos``."""
    rng = np.random.default_rng(seed)
    images = []
    for path in orthos:
        with GeoRaster(path) as raster:
            images.append(raster.read_rgb())
    crops = []
    for k in range(count):
        image = images[k % len(images)]
        h, w = sizes[k % len(sizes)]
        h, w = min(h, image.shape[0]), min(w, image.shape[1])
        y, x = int(rng.integers(0, image.shape[0] - h + 1)), int(rng.integers(0, image.shape[1] - w + 1))
        crops.append(np.ascontiguousarray(image[y : y + h, x : x + w]))
    return crops


# --- writing ----------------------------------------------------------------------------------


def write_onnx(proto: onnx.ModelProto, record: OnnxRecord, out: Path) -> None:
    """The graph with its record as metadata, in one file, written atomically."""
    del proto.metadata_props[:]
    for key, value in record.metadata().items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.producer_name = "orthonav"
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        onnx.save_model(proto, str(tmp))
