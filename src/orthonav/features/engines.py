"""What the learned backends' engines share: for the torch engine, the device and threads, weight
loading with clear errors, no-grad calls and image/feature conversion; for either engine, the
extraction of the strongest keypoints by top-k (ALIKED's and DISK's).

Each model's module (:mod:`.aliked`, :mod:`.disk`, :mod:`.xfeat`, :mod:`.lightglue`) holds its
torch and ONNX Runtime engines side by side, and a companion with ONNX Runtime alone imports it. So
torch and the packages built on it are imported where a torch engine is made or called, never when
a module is imported: this module's torch code imports torch in its functions.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ParamSpec, TypeVar

import numpy as np

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureBackend, FeatureSet, Matches, Runtime

if TYPE_CHECKING:
    import torch
    from torch import nn

Params = ParamSpec("Params")
Result = TypeVar("Result")


def inference_mode(method: Callable[Params, Result]) -> Callable[Params, Result]:
    """``method`` run under ``torch.inference_mode`` (torch's decorator, with torch imported on the
    first call rather than where the method is defined)."""

    @functools.wraps(method)
    def run(*args: Params.args, **kwargs: Params.kwargs) -> Result:
        import torch

        with torch.inference_mode():
            return method(*args, **kwargs)

    return run


def resolve_device(runtime: Runtime) -> torch.device:
    """The torch device for ``runtime``, or a clear error when CUDA is asked for but absent."""
    import torch

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
    import torch

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
    import torch

    if not len(query_idx):
        return Matches.empty()
    order = torch.argsort(confidence, descending=True, stable=True)[:max_matches]
    pairs = torch.stack([query_idx[order], train_idx[order]], 1)
    return Matches(pairs.cpu().numpy().astype(np.int64), (1.0 - confidence[order]).float().cpu().numpy())


class TorchBackend(FeatureBackend):
    """A backend whose networks run in torch on ``runtime.device`` (eval mode, no grad)."""

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        import torch

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
        import torch

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


def keypoints_asked(limit: int | None, mask: np.ndarray | None, most: int) -> int:
    """The keypoints to select over the whole image so that about ``limit`` fall inside ``mask``
    (the warped frame's valid part), at most ``most`` (the map's count; all for None). ALIKED's
    descriptor head costs per keypoint, so fewer selected is a faster extraction, and the strongest
    ``limit`` of them are mostly those of the full count (docs/benchmarks/localize.md)."""
    if limit is None or limit >= most:
        return most
    share = 1.0 if mask is None else np.count_nonzero(mask) / mask.size
    return min(most, math.ceil(limit / max(share, limit / most)))


class TopKExtraction:
    """``extract`` and ``extract_strongest`` of an extractor that selects its K strongest
    keypoints by top-k (ALIKED and DISK under either engine): where fewer are kept, fewer are
    selected and described. The engine gives ``_extract(gray, mask, count)``."""

    conf: dict[str, Any]

    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        return self._extract(gray, mask, int(self.conf["max_keypoints"]))

    def extract_strongest(self, gray: np.ndarray, mask: np.ndarray | None, limit: int | None) -> FeatureSet:
        asked = keypoints_asked(limit, mask, int(self.conf["max_keypoints"]))
        return self._extract(gray, mask, asked).strongest(limit)

    def _extract(self, gray: np.ndarray, mask: np.ndarray | None, count: int) -> FeatureSet:
        raise NotImplementedError
