"""What the learned (torch) backends share: device and threads, weight loading with clear
errors, image/feature conversion, and batched frame-vs-tiles matching for LightGlue-style
matchers.

Batched matching: the candidate tiles' keypoints are padded to one
length and the frame is matched against all of them in a single pass through the
transformer, with attention masks keeping padding out; the final assignment is then read
per tile on its unpadded part. Adaptive depth and point pruning are off in this path, so
it gives the same matches as the network run on one pair at a time without them.

A CPU is compute-bound: one padded pass over B tiles costs what B single passes cost, and
the single pass can prune points and stop early (about 25 % faster, measured). So the
padded batch is the default on CUDA and the per-pair pass, with the network's own adaptive
depth and width, the default on CPU.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureBackend, FeatureSet, Matches, Runtime


def resolve_device(runtime: Runtime) -> torch.device:
    """The torch device for ``runtime``, or a clear error when CUDA is asked for but absent."""
    if runtime.device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise OrthonavError(
                f"device {runtime.device!r}: CUDA is not available here (torch {torch.__version__}, "
                "no usable GPU); use --device cpu"
            )
        index = int(runtime.device.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise OrthonavError(
                f"device {runtime.device!r}: only {torch.cuda.device_count()} CUDA device(s) present"
            )
    return torch.device(runtime.device)


def load_weights(module: nn.Module, path: str | Path, what: str) -> None:
    """Load a state dict file into ``module``; every mismatch is a clear, named error."""
    path = Path(path)
    if not path.is_file():
        raise OrthonavError(f"{what} weights {path}: no such file")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a file that is not a checkpoint
        raise OrthonavError(
            f"{what} weights {path}: not a torch state dict ({exc.__class__.__name__})"
        ) from None
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise OrthonavError(f"{what} weights {path}: expected a dict of tensors (a state dict)")
    expected = module.state_dict()
    # BatchNorm's step counter is unused in eval mode; files saved without it are fine.
    state = {**{k: v for k, v in expected.items() if k.endswith("num_batches_tracked")}, **state}
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise OrthonavError(
            f"{what} weights {path}: not this architecture "
            f"(missing {_few(missing)}; unexpected {_few(unexpected)})"
        )
    wrong = [k for k, v in state.items() if v.shape != expected[k].shape]
    if wrong:
        k = wrong[0]
        raise OrthonavError(
            f"{what} weights {path}: {len(wrong)} tensor(s) of the wrong shape, e.g. {k} is "
            f"{tuple(state[k].shape)}, expected {tuple(expected[k].shape)}"
        )
    module.load_state_dict(state)


def _few(keys: list[str]) -> str:
    return (
        "none" if not keys else ", ".join(keys[:3]) + (f" and {len(keys) - 3} more" if len(keys) > 3 else "")
    )


def best_matches(
    query_idx: torch.Tensor, train_idx: torch.Tensor, confidence: torch.Tensor, max_matches: int
) -> Matches:
    """Index pairs ordered by confidence (higher is better), at most ``max_matches``;
    distance = 1 - confidence, so lower is better as :class:`Matches` expects."""
    if not len(query_idx):
        return Matches.empty()
    order = torch.argsort(confidence, descending=True, stable=True)[:max_matches]
    pairs = torch.stack([query_idx[order], train_idx[order]], 1)
    return Matches(pairs.cpu().numpy().astype(np.int64), (1.0 - confidence[order]).float().cpu().numpy())


class TorchBackend(FeatureBackend):
    """A backend whose networks run in torch on ``runtime.device`` (eval mode, no grad)."""

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        self.device = resolve_device(self.runtime)
        if self.runtime.threads:
            torch.set_num_threads(self.runtime.threads)
        # Same input, same features: no autotuned (nondeterministic) kernels.
        torch.backends.cudnn.benchmark = False
        torch.backends.cudnn.deterministic = True

    @property
    def engine(self) -> str:
        return f"torch on {self.device}"

    def image_tensor(self, gray: np.ndarray) -> torch.Tensor:
        """(H, W) uint8 -> (1, 1, H, W) float in [0, 1] on the backend's device."""
        return torch.from_numpy(np.ascontiguousarray(gray)).to(self.device, torch.float32)[None, None] / 255.0

    def to_featureset(
        self, keypoints: torch.Tensor, descriptors: torch.Tensor, scores: torch.Tensor, gray: np.ndarray
    ) -> FeatureSet:
        return FeatureSet(
            keypoints.detach().float().cpu().numpy().reshape(-1, 2),
            descriptors.detach().float().cpu().numpy().reshape(len(keypoints), descriptors.shape[-1]),
            scores.detach().float().cpu().numpy().reshape(-1),
            (gray.shape[1], gray.shape[0]),
        )

    @property
    def descriptor_dtype(self) -> np.dtype:
        return np.dtype(np.float32)


class GlueBatch:
    """Match one feature set against many with a LightGlue-style network in one padded pass.

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
        if features.image_size is None:
            raise OrthonavError("learned matching needs the image size of each feature set")
        size = torch.tensor(features.image_size, dtype=torch.float32, device=self.device)
        kpts = torch.from_numpy(features.keypoints).to(self.device, torch.float32)
        return (kpts - size / 2) / (size.max() / 2)

    @torch.inference_mode()
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
        m0, _, mscores0, _ = self.filter_matches(log_assignment, self.threshold)
        valid = m0[0] > -1
        return best_matches(
            torch.nonzero(valid).flatten(), m0[0][valid], mscores0[0][valid], self.max_matches
        )
