"""CNN trunks for dense correlation: torchvision VGG11, ResNet18 and MobileNetV2, cut short.

The classifier is removed and the trunk is truncated at a stage (a higher stage sees more
context but has a coarser stride); the output is L2-normalised per location over channels,
so the correlation of two feature maps is a sum of cosines (the correlation surface H(u, v)).

Model files (``torch.save``) hold the architecture with the weights, so a file of another
architecture is refused by name, not by a state-dict error.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torchvision import models

from orthonav.atomic import atomic_path
from orthonav.errors import OrthonavError
from orthonav.frames.views import Views
from orthonav.models.heatmap import Heatmap

MODEL_FORMAT = "orthonav-correction-model"
MODEL_VERSION = 1


@dataclass(frozen=True)
class _Arch:
    build: Any  # () -> (list of stage modules)
    default_stage: int
    strides: tuple[int, ...]  # output stride after each stage


def _vgg11_stages() -> list[nn.Module]:
    layers = list(models.vgg11(weights=None).features)
    # Convs of each block, the block's pooling at the start of the next (ends: 2, 5, 10, 15, 20).
    bounds = [0, 2, 5, 10, 15, 20]
    return [nn.Sequential(*layers[a:b]) for a, b in itertools.pairwise(bounds)]


def _resnet18_stages() -> list[nn.Module]:
    net = models.resnet18(weights=None)
    stem = nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool, net.layer1)
    return [stem, net.layer2, net.layer3, net.layer4]


def _mobilenetv2_stages() -> list[nn.Module]:
    layers = list(models.mobilenet_v2(weights=None).features)
    bounds = [0, 2, 4, 7, 14, 18]
    return [nn.Sequential(*layers[a:b]) for a, b in itertools.pairwise(bounds)]


ARCHITECTURES: dict[str, _Arch] = {
    "vgg11": _Arch(_vgg11_stages, 3, (1, 2, 4, 8, 16)),
    "resnet18": _Arch(_resnet18_stages, 1, (4, 8, 16, 32)),
    "mobilenetv2": _Arch(_mobilenetv2_stages, 3, (2, 4, 8, 16, 32)),
}


class DenseFeatures(nn.Module):
    """Image (B, 3, H, W) -> L2-normalised features (B, C, H / stride, W / stride)."""

    def __init__(self, backbone: str, stage: int | None = None) -> None:
        super().__init__()
        if backbone not in ARCHITECTURES:
            raise OrthonavError(f"backbone {backbone!r}: expected one of {', '.join(ARCHITECTURES)}")
        arch = ARCHITECTURES[backbone]
        stage = arch.default_stage if stage is None else int(stage)
        if not 1 <= stage <= len(arch.strides):
            raise OrthonavError(f"{backbone} stage: expected 1..{len(arch.strides)}, got {stage}")
        self.backbone, self.stage, self.stride = backbone, stage, arch.strides[stage - 1]
        self.trunk = nn.Sequential(*arch.build()[:stage])

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.trunk(images), dim=1)

    # The calls the corrector makes, shared with orthonav.models.onnx.graphs.OnnxTrunk.

    def image_features(self, rgb: np.ndarray, mask: np.ndarray) -> torch.Tensor:
        """(1, C, h, w) features of one view."""
        return image_features(self, rgb, mask)

    def feature_heatmap(self, views: Views, region: torch.Tensor) -> Heatmap:
        """The frame view's features correlated over precomputed ``region`` features."""
        return feature_heatmap(self, views, region)

    @staticmethod
    def as_array(features: torch.Tensor) -> np.ndarray:
        """(C, h, w) of one view's features, for pictures."""
        return features[0].numpy()


def to_tensor(rgb: np.ndarray, mask: np.ndarray | None = None) -> torch.Tensor:
    """(H, W, 3) uint8 -> (3, H, W) float, standardised per channel over the valid pixels.

    Per-image standardisation removes most of a date's colour and exposure before the
    network sees it; invalid pixels become 0 (the mean).
    """
    image = torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1).float()
    valid = torch.ones(image.shape[1:], dtype=torch.bool) if mask is None else torch.from_numpy(mask)
    pixels = image[:, valid] if valid.any() else image.reshape(3, -1)
    mean = pixels.mean(dim=1, keepdim=True)
    std = pixels.std(dim=1, keepdim=True).clamp_min(1.0)
    out = (image - mean[:, :, None]) / std[:, :, None]
    return out * valid


def correlate(region: torch.Tensor, template: torch.Tensor, template_valid: torch.Tensor) -> torch.Tensor:
    """Mean cosine similarity of each template over its region, for a batch (one conv2d).

    region (B, C, H, W), template (B, C, h, w), template_valid (B, 1, h, w) -> (B, H-h+1, W-w+1).
    """
    b, c = template.shape[:2]
    template = template * template_valid
    heat = F.conv2d(region.reshape(1, b * c, *region.shape[2:]), template, groups=b)[0]
    return heat / template_valid.flatten(1).sum(dim=1).clamp_min(1.0)[:, None, None]


def image_features(network: DenseFeatures, rgb: np.ndarray, mask: np.ndarray) -> torch.Tensor:
    """(1, C, h, w) features of one view (no gradients kept)."""
    with torch.inference_mode():
        return network(to_tensor(rgb, mask)[None])


def feature_heatmap(network: DenseFeatures, views: Views, region: torch.Tensor) -> Heatmap:
    """The frame view's features correlated over precomputed ``region`` features."""
    frame = image_features(network, views.frame, views.frame_mask)
    with torch.inference_mode():
        valid = valid_cells(torch.from_numpy(views.frame_mask)[None, None], tuple(frame.shape[2:]))
        heat = correlate(region, frame, valid)[0]
    return Heatmap(heat.numpy().astype(np.float32), network.stride)


def valid_cells(masks: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """(B, 1, H, W) pixel masks -> (B, 1, rows, cols) float masks of feature cells that hold imagery."""
    return (F.adaptive_avg_pool2d(masks.float(), shape) > 0.99).float()


def write_model_file(
    path: Path, model_format: str, version: int, net: nn.Module, fields: dict, info: dict
) -> None:
    """Architecture ``fields`` and half-precision weights in one file, written atomically (half
    precision keeps the file small enough to ship)."""
    payload = {
        "format": model_format,
        "version": version,
        **fields,
        "state_dict": {k: v.half() if v.is_floating_point() else v for k, v in net.state_dict().items()},
        "info": info,
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def read_model_file(path: str | Path, model_format: str, version: int, kind: str, writer: str) -> dict:
    """A model file's checked payload, weights back in float32; clear errors for a missing,
    foreign (``kind`` names what was expected, ``writer`` the command that writes it) or
    other-version file."""
    path = Path(path)
    if not path.is_file():
        raise OrthonavError(f"{path}: no such {kind} file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign or damaged files
        raise OrthonavError(f"{path}: not a readable model file ({type(exc).__name__}: {exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != model_format:
        raise OrthonavError(f"{path}: not an orthonav {kind} (expected a file written by `{writer}`)")
    if payload.get("version") != version:
        raise OrthonavError(f"{path}: {kind} format version {payload.get('version')}, expected {version}")
    state = payload["state_dict"]
    payload["state_dict"] = {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
    return payload


def save_model(net: DenseFeatures, path: Path, info: dict) -> None:
    """Write a correction model file."""
    write_model_file(
        path, MODEL_FORMAT, MODEL_VERSION, net, {"backbone": net.backbone, "stage": net.stage}, info
    )


def load_model(path: str | Path) -> tuple[DenseFeatures, dict]:
    """A model file -> (network in eval mode, its recorded info); clear errors for wrong files."""
    payload = read_model_file(
        path, MODEL_FORMAT, MODEL_VERSION, "correction model", "orthonav correction train"
    )
    net = DenseFeatures(payload["backbone"], payload["stage"])
    state = payload["state_dict"]
    missing, unexpected = _compare_keys(net, state)
    if missing or unexpected or _shape_mismatch(net, state):
        raise OrthonavError(
            f"{path}: its weights do not fit a {payload['backbone']} trunk cut at stage {payload['stage']} "
            f"(missing {len(missing)}, unexpected {len(unexpected)} or differently shaped tensors)"
        )
    net.load_state_dict(state)
    return net.eval(), dict(payload.get("info", {}))


def _compare_keys(net: nn.Module, state: dict) -> tuple[set, set]:
    own = set(net.state_dict())
    return own - set(state), set(state) - own


def _shape_mismatch(net: nn.Module, state: dict) -> bool:
    return any(v.shape != state[k].shape for k, v in net.state_dict().items() if k in state)
