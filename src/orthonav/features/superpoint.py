"""SuperPoint keypoints matched by SuperGlue, written here in plain torch.

Why our own code: the reference (MagicLeap's SuperGluePretrainedNetwork; DeTone et al. 2018,
Sarlin et al. 2020) is no installable package, and its weights may not be redistributed, so
orthonav ships neither. The networks below are the published architectures with the very
same state-dict key names, so a user's ``superpoint_v1.pth`` and ``superglue_outdoor.pth``
load unchanged.

Two departures from the reference demo, both for the localizer: images are zero-padded to a
multiple of 8 instead of resized (keypoints in the padding are dropped), and a frame is
matched against all candidate tiles in one padded SuperGlue pass (attention masks keep the
padding out); the optimal transport is then solved per tile on its unpadded part, so batched
and one-pair-at-a-time matching give the same matches.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from copy import deepcopy
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from orthonav.errors import OrthonavError
from orthonav.features.base import FeatureSet, Matches, Runtime, register
from orthonav.features.engines import TorchBackend, best_matches, load_weights

CELL = 8  # SuperPoint works on 8 x 8 pixel cells: one detector/descriptor vector each
DESCRIPTOR_DIM = 256
NUM_HEADS = 4
NO_WEIGHTS = (
    "feature backend 'superpoint' needs the public SuperPoint and SuperGlue weights, which are "
    "not redistributable and so not shipped with orthonav; download superpoint_v1.pth and "
    "superglue_outdoor.pth from MagicLeap's SuperGluePretrainedNetwork and pass them with "
    "--weights superpoint_v1.pth,superglue_outdoor.pth on the CLI, or as the config keys "
    "superpoint_weights= and superglue_weights="
)


# --- SuperPoint ---------------------------------------------------------------------------


class SuperPointNet(nn.Module):
    """SuperPoint: a VGG-style encoder (1/8 resolution), a detector and a descriptor head."""

    def __init__(self) -> None:
        super().__init__()
        c1, c2, c3, c4, c5 = 64, 64, 128, 128, 256
        self.conv1a = _conv3(1, c1)
        self.conv1b = _conv3(c1, c1)
        self.conv2a = _conv3(c1, c2)
        self.conv2b = _conv3(c2, c2)
        self.conv3a = _conv3(c2, c3)
        self.conv3b = _conv3(c3, c3)
        self.conv4a = _conv3(c3, c4)
        self.conv4b = _conv3(c4, c4)
        self.convPa = _conv3(c4, c5)
        self.convPb = nn.Conv2d(c5, CELL * CELL + 1, kernel_size=1)
        self.convDa = _conv3(c4, c5)
        self.convDb = nn.Conv2d(c5, DESCRIPTOR_DIM, kernel_size=1)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 1, H, W) in [0, 1], H and W multiples of 8 -> detector logits (B, 65, H/8, W/8)
        and L2-normalised coarse descriptors (B, 256, H/8, W/8)."""
        x = image
        blocks = [
            (self.conv1a, self.conv1b),
            (self.conv2a, self.conv2b),
            (self.conv3a, self.conv3b),
            (self.conv4a, self.conv4b),
        ]
        for i, (conv_a, conv_b) in enumerate(blocks):
            if i:
                x = F.max_pool2d(x, kernel_size=2, stride=2)
            x = F.relu(conv_b(F.relu(conv_a(x))))
        logits = self.convPb(F.relu(self.convPa(x)))
        descriptors = F.normalize(self.convDb(F.relu(self.convDa(x))), p=2, dim=1)
        return logits, descriptors


def _conv3(c_in: int, c_out: int) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, kernel_size=3, stride=1, padding=1)


def dense_scores(logits: torch.Tensor) -> torch.Tensor:
    """(B, 65, h, w) detector logits -> (B, 8h, 8w) keypoint probabilities.

    Softmax over the 64 cell positions and the "no keypoint" dustbin, drop the dustbin, and
    put channel ``8 dy + dx`` of cell (i, j) at pixel (8 i + dy, 8 j + dx).
    """
    return F.pixel_shuffle(F.softmax(logits, dim=1)[:, :-1], CELL)[:, 0]


def simple_nms(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """Zero every score that is not the maximum of its (2 radius + 1)^2 neighbourhood (reference NMS)."""
    if radius < 0:
        raise OrthonavError(f"nms_radius: expected >= 0, got {radius}")

    def max_pool(x: torch.Tensor) -> torch.Tensor:
        return F.max_pool2d(x, kernel_size=radius * 2 + 1, stride=1, padding=radius)

    zeros = torch.zeros_like(scores)
    max_mask = scores == max_pool(scores)
    for _ in range(2):
        supp_mask = max_pool(max_mask.float()) > 0
        supp_scores = torch.where(supp_mask, zeros, scores)
        new_max_mask = supp_scores == max_pool(supp_scores)
        max_mask = max_mask | (new_max_mask & (~supp_mask))
    return torch.where(max_mask, scores, zeros)


def detect(
    scores: torch.Tensor, size: tuple[int, int], threshold: float, border: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Keypoints (N, 2) float (x, y) and scores (N,) above ``threshold`` in an (H, W) score map.

    Only pixels at least ``border`` px inside the image of ``size`` (width, height) are kept,
    which also drops everything in the padding right and below it.
    """
    width, height = size
    rows_cols = torch.nonzero(scores > threshold)
    row, col = rows_cols[:, 0], rows_cols[:, 1]
    keep = (row >= border) & (row < height - border) & (col >= border) & (col < width - border)
    rows_cols = rows_cols[keep]
    return rows_cols.flip(1).float(), scores[rows_cols[:, 0], rows_cols[:, 1]]


def keypoints_from_logits(
    logits: torch.Tensor, size: tuple[int, int], threshold: float, nms_radius: int, border: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The decoding of one image's (1, 65, h, w) detector logits: probabilities, NMS, threshold, borders."""
    return detect(simple_nms(dense_scores(logits), nms_radius)[0], size, threshold, border)


def sample_descriptors(keypoints: torch.Tensor, descriptors: torch.Tensor, s: int = CELL) -> torch.Tensor:
    """Bilinearly sample (1, D, h, w) coarse descriptors at (N, 2) pixel keypoints -> (N, D), unit norm.

    The reference's mapping from pixels to the coarse grid, kept as is so that the published
    weights see what they were trained with.
    """
    _, dim, h, w = descriptors.shape
    grid = keypoints - s / 2 + 0.5
    grid = grid / grid.new_tensor([w * s - s / 2 - 0.5, h * s - s / 2 - 0.5])
    grid = grid * 2 - 1
    sampled = F.grid_sample(descriptors, grid.view(1, 1, -1, 2), mode="bilinear", align_corners=True)
    return F.normalize(sampled.reshape(dim, -1), p=2, dim=0).t()


# --- SuperGlue ----------------------------------------------------------------------------


def mlp(channels: list[int]) -> nn.Sequential:
    """1x1 Conv1d layers with BatchNorm1d + ReLU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i in range(1, len(channels)):
        layers.append(nn.Conv1d(channels[i - 1], channels[i], kernel_size=1, bias=True))
        if i < len(channels) - 1:
            layers += [nn.BatchNorm1d(channels[i]), nn.ReLU()]
    return nn.Sequential(*layers)


def normalize_keypoints(keypoints: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """(N, 2) pixels -> centred on the image of ``size`` (w, h), scaled by 0.7 of its larger side."""
    wh = keypoints.new_tensor(size)
    return (keypoints - wh / 2) / (wh.max() * 0.7)


class KeypointEncoder(nn.Module):
    """Embeds (x, y, score) of each keypoint into the descriptor space."""

    def __init__(self, dim: int = DESCRIPTOR_DIM, layers: Sequence[int] = (32, 64, 128, 256)) -> None:
        super().__init__()
        self.encoder = mlp([3, *layers, dim])
        nn.init.constant_(self.encoder[-1].bias, 0.0)

    def forward(self, keypoints: torch.Tensor, scores: torch.Tensor) -> torch.Tensor:
        """(B, N, 2) normalised keypoints and (B, N) scores -> (B, D, N)."""
        return self.encoder(torch.cat([keypoints.transpose(1, 2), scores.unsqueeze(1)], dim=1))


def attention(
    query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, key_mask: torch.Tensor | None
) -> torch.Tensor:
    """Scaled dot-product attention on (B, d, H, N) heads; ``key_mask`` (B, M) False for padding."""
    scores = torch.einsum("bdhn,bdhm->bhnm", query, key) / query.shape[1] ** 0.5
    if key_mask is not None:
        scores = scores.masked_fill(~key_mask[:, None, None, :], float("-inf"))
    return torch.einsum("bhnm,bdhm->bdhn", F.softmax(scores, dim=-1), value)


class MultiHeadedAttention(nn.Module):
    """Multi-head attention with 1x1 Conv1d projections, channels laid out (dim, heads) as published."""

    def __init__(self, num_heads: int, d_model: int) -> None:
        super().__init__()
        self.dim = d_model // num_heads
        self.num_heads = num_heads
        self.merge = nn.Conv1d(d_model, d_model, kernel_size=1)
        self.proj = nn.ModuleList([deepcopy(self.merge) for _ in range(3)])

    def forward(
        self, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor, key_mask: torch.Tensor | None
    ) -> torch.Tensor:
        b = query.shape[0]
        q, k, v = (
            proj(x).view(b, self.dim, self.num_heads, -1)
            for proj, x in zip(self.proj, (query, key, value), strict=True)
        )
        x = attention(q, k, v, key_mask)
        return self.merge(x.contiguous().view(b, self.dim * self.num_heads, -1))


class AttentionalPropagation(nn.Module):
    """One GNN layer: a message from ``source`` by attention, then an MLP on [x, message]."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.attn = MultiHeadedAttention(num_heads, dim)
        self.mlp = mlp([dim * 2, dim * 2, dim])
        nn.init.constant_(self.mlp[-1].bias, 0.0)

    def forward(
        self, x: torch.Tensor, source: torch.Tensor, source_mask: torch.Tensor | None
    ) -> torch.Tensor:
        message = self.attn(x, source, source, source_mask)
        return self.mlp(torch.cat([x, message], dim=1))


class AttentionalGNN(nn.Module):
    """Alternating self- and cross-attention layers updating both descriptor sets residually."""

    def __init__(self, dim: int, layer_names: list[str]) -> None:
        super().__init__()
        self.layers = nn.ModuleList([AttentionalPropagation(dim, NUM_HEADS) for _ in layer_names])
        self.names = layer_names

    def forward(
        self,
        desc0: torch.Tensor,
        desc1: torch.Tensor,
        mask0: torch.Tensor | None = None,
        mask1: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, D, M) and (B, D, N) descriptors; masks (B, M) / (B, N) False where padded (None: all valid)."""
        for layer, name in zip(self.layers, self.names, strict=True):
            if name == "cross":
                delta0, delta1 = layer(desc0, desc1, mask1), layer(desc1, desc0, mask0)
            else:
                delta0, delta1 = layer(desc0, desc0, mask0), layer(desc1, desc1, mask1)
            desc0, desc1 = desc0 + delta0, desc1 + delta1
        return desc0, desc1


class SuperGlueNet(nn.Module):
    """SuperGlue: keypoint encoder, attentional GNN (``gnn_layers``, alternating self/cross),
    final projection and the learned dustbin score for the optimal transport."""

    def __init__(self, gnn_layers: int = 18) -> None:
        super().__init__()
        self.kenc = KeypointEncoder(DESCRIPTOR_DIM)
        self.gnn = AttentionalGNN(DESCRIPTOR_DIM, [("self", "cross")[i % 2] for i in range(gnn_layers)])
        self.final_proj = nn.Conv1d(DESCRIPTOR_DIM, DESCRIPTOR_DIM, kernel_size=1, bias=True)
        self.bin_score = nn.Parameter(torch.tensor(1.0))

    def propagate(
        self,
        kpts0: torch.Tensor,
        scores0: torch.Tensor,
        desc0: torch.Tensor,
        kpts1: torch.Tensor,
        scores1: torch.Tensor,
        desc1: torch.Tensor,
        mask1: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Normalised keypoints (B, N, 2), scores (B, N), descriptors (B, D, N) -> GNN outputs."""
        desc0 = desc0 + self.kenc(kpts0, scores0)
        desc1 = desc1 + self.kenc(kpts1, scores1)
        return self.gnn(desc0, desc1, None, mask1)

    def log_assignment(self, desc0: torch.Tensor, desc1: torch.Tensor, iterations: int) -> torch.Tensor:
        """GNN outputs (B, D, M), (B, D, N) -> log assignment (B, M + 1, N + 1) with dustbins."""
        mdesc0, mdesc1 = self.final_proj(desc0), self.final_proj(desc1)
        scores = torch.einsum("bdn,bdm->bnm", mdesc0, mdesc1) / DESCRIPTOR_DIM**0.5
        return log_optimal_transport(scores, self.bin_score, iterations)


def log_optimal_transport(scores: torch.Tensor, alpha: torch.Tensor, iterations: int) -> torch.Tensor:
    """Sinkhorn in log space on (B, M, N) scores augmented with a dustbin row and column of score
    ``alpha``; returns the log assignment (B, M + 1, N + 1), scaled so a match has probability <= 1."""
    b, m, n = scores.shape
    ms, ns = scores.new_tensor(float(m)), scores.new_tensor(float(n))
    alpha = alpha.to(scores)
    couplings = torch.cat(
        [
            torch.cat([scores, alpha.expand(b, m, 1)], -1),
            torch.cat([alpha.expand(b, 1, n), alpha.expand(b, 1, 1)], -1),
        ],
        1,
    )
    norm = -(ms + ns).log()
    log_mu = torch.cat([norm.expand(m), ns.log()[None] + norm])[None].expand(b, -1)
    log_nu = torch.cat([norm.expand(n), ms.log()[None] + norm])[None].expand(b, -1)
    u, v = torch.zeros_like(log_mu), torch.zeros_like(log_nu)
    for _ in range(iterations):
        u = log_mu - torch.logsumexp(couplings + v.unsqueeze(1), dim=2)
        v = log_nu - torch.logsumexp(couplings + u.unsqueeze(2), dim=1)
    return couplings + u.unsqueeze(2) + v.unsqueeze(1) - norm


def mutual_matches(log_assignment: torch.Tensor, threshold: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Mutual nearest neighbours of a (B, M + 1, N + 1) log assignment with probability > ``threshold``.

    Returns, per query point, the train index (-1: unmatched) and the match probability.
    """
    inner = log_assignment[:, :-1, :-1]
    max0, max1 = inner.max(2), inner.max(1)
    indices0, indices1 = max0.indices, max1.indices
    arange0 = torch.arange(indices0.shape[1], device=inner.device)[None]
    mutual0 = arange0 == indices1.gather(1, indices0)
    mscores0 = torch.where(mutual0, max0.values.exp(), inner.new_tensor(0.0))
    valid0 = mutual0 & (mscores0 > threshold)
    return torch.where(valid0, indices0, indices0.new_tensor(-1)), mscores0


# --- the backend --------------------------------------------------------------------------


@register("superpoint")
class SuperPointBackend(TorchBackend):
    """SuperPoint features matched by SuperGlue; the user supplies the public weight files."""

    rotation_invariant = False  # neither network was trained for arbitrary in-plane rotation
    default_conf: ClassVar[dict[str, Any]] = {
        "superpoint_weights": None,
        "superglue_weights": None,
        "max_keypoints": 1024,
        "keypoint_threshold": 0.005,
        "nms_radius": 4,
        "remove_borders": 4,
        "gnn_layers": 18,
        "sinkhorn_iterations": 100,
        "match_threshold": 0.2,
        "max_matches": 300,
    }

    def __init__(self, runtime: Runtime | None = None, **conf: Any) -> None:
        super().__init__(runtime, **conf)
        c = self.conf
        _check_conf(c)
        if c["superpoint_weights"] is None or c["superglue_weights"] is None:
            raise OrthonavError(NO_WEIGHTS)
        self.superpoint = SuperPointNet()
        load_weights(self.superpoint, c["superpoint_weights"], "SuperPoint")
        self.superglue = SuperGlueNet(c["gnn_layers"])
        _load_superglue(self.superglue, c["superglue_weights"], c["gnn_layers"])
        self.superpoint.eval().to(self.device)
        self.superglue.eval().to(self.device)

    @torch.inference_mode()
    def extract(self, gray: np.ndarray, mask: np.ndarray | None = None) -> FeatureSet:
        _check_image(gray, mask)
        h, w = gray.shape
        image = F.pad(self.image_tensor(gray), (0, -w % CELL, 0, -h % CELL))  # zeros right and below
        logits, coarse = self.superpoint(image)
        c = self.conf
        kpts, scores = keypoints_from_logits(
            logits, (w, h), c["keypoint_threshold"], c["nms_radius"], c["remove_borders"]
        )
        if not len(kpts):
            return dataclasses.replace(self.empty(), image_size=(w, h))
        features = self.to_featureset(kpts, sample_descriptors(kpts, coarse), scores, gray).inside(mask)
        return _strongest(features, c["max_keypoints"])

    def match(self, query: FeatureSet, train: FeatureSet) -> Matches:
        return self.match_many(query, [train])[0]

    @torch.inference_mode()
    def match_many(self, query: FeatureSet, trains: Sequence[FeatureSet]) -> list[Matches]:
        """Encoder and GNN once for all tiles (padded batch, the query repeated); the optimal
        transport and mutual check per tile on its unpadded part."""
        out = [Matches.empty() for _ in trains]
        used = [i for i, t in enumerate(trains) if len(t) >= 2]
        if len(query) < 2 or not used:
            return out
        b, m, n = len(used), len(query), max(len(trains[i]) for i in used)
        k0, s0, d0 = self._inputs(query)
        kpts0, scores0, desc0 = k0[None].expand(b, m, 2), s0[None].expand(b, m), d0[None].expand(b, -1, m)
        kpts1 = torch.zeros(b, n, 2, device=self.device)
        scores1 = torch.zeros(b, n, device=self.device)
        desc1 = torch.zeros(b, DESCRIPTOR_DIM, n, device=self.device)
        mask1 = torch.zeros(b, n, dtype=torch.bool, device=self.device)
        for j, i in enumerate(used):
            k = len(trains[i])
            kpts1[j, :k], scores1[j, :k], desc1[j, :, :k] = self._inputs(trains[i])
            mask1[j, :k] = True
        desc0, desc1 = self.superglue.propagate(kpts0, scores0, desc0, kpts1, scores1, desc1, mask1)
        for j, i in enumerate(used):
            k = len(trains[i])
            z = self.superglue.log_assignment(
                desc0[j : j + 1], desc1[j : j + 1, :, :k], self.conf["sinkhorn_iterations"]
            )
            out[i] = self._matches(z)
        return out

    def _inputs(self, features: FeatureSet) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Normalised keypoints (N, 2), scores (N,), descriptors (D, N) on the device."""
        if features.image_size is None:
            raise OrthonavError("SuperGlue matching needs the image size of each feature set")
        if features.descriptors.ndim != 2 or features.descriptors.shape[1] != DESCRIPTOR_DIM:
            raise OrthonavError(
                f"SuperGlue matching needs {DESCRIPTOR_DIM}-d SuperPoint descriptors, "
                f"got shape {features.descriptors.shape}"
            )
        kpts = torch.from_numpy(np.asarray(features.keypoints)).to(self.device, torch.float32)
        scores = torch.from_numpy(np.asarray(features.scores)).to(self.device, torch.float32)
        desc = torch.from_numpy(np.asarray(features.descriptors)).to(self.device, torch.float32)
        return normalize_keypoints(kpts, features.image_size), scores, desc.t()

    def _matches(self, log_assignment: torch.Tensor) -> Matches:
        indices0, mscores0 = mutual_matches(log_assignment, self.conf["match_threshold"])
        valid = indices0[0] > -1
        return best_matches(
            torch.nonzero(valid).flatten(), indices0[0][valid], mscores0[0][valid], self.conf["max_matches"]
        )

    @property
    def descriptor_size(self) -> int:
        return DESCRIPTOR_DIM


def _strongest(features: FeatureSet, k: int) -> FeatureSet:
    """The ``k`` highest-scoring features, best first (all when ``k`` < 0, as in the reference)."""
    order = np.argsort(-features.scores, kind="stable")
    return features.subset(order if k < 0 else order[:k])


def _check_image(gray: np.ndarray, mask: np.ndarray | None) -> None:
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise OrthonavError(f"SuperPoint expects an (H, W) uint8 image, got {gray.shape} {gray.dtype}")
    if mask is not None and mask.shape != gray.shape:
        raise OrthonavError(f"mask shape {mask.shape} differs from the image's {gray.shape}")


def _check_conf(c: dict[str, Any]) -> None:
    """Values out of range are user errors, named here rather than failing deep inside torch."""
    minimum = {
        "gnn_layers": 1,
        "sinkhorn_iterations": 1,
        "nms_radius": 0,
        "remove_borders": 0,
        "max_matches": 1,
        "max_keypoints": -1,
    }
    for key, low in minimum.items():
        value = c[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise OrthonavError(
                f"feature backend 'superpoint': {key} must be an integer >= {low}, got {value!r}"
            )
    for key in ("keypoint_threshold", "match_threshold"):
        if not 0.0 <= float(c[key]) < 1.0:
            raise OrthonavError(f"feature backend 'superpoint': {key} must be in [0, 1), got {c[key]!r}")


def _load_superglue(net: SuperGlueNet, path: str | Path, gnn_layers: int) -> None:
    """``load_weights``, with a hint when the layer count of the file and the config differ."""
    try:
        load_weights(net, path, "SuperGlue")
    except OrthonavError as exc:
        if "not this architecture" not in str(exc):
            raise
        raise OrthonavError(
            f"{exc}; if this is a SuperGlue file, its GNN layer count must equal gnn_layers "
            f"(now {gnn_layers}; the published weights have 18)"
        ) from None
