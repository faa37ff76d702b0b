"""A global descriptor that survives a change of date: the correction trunk, pooled by a small head.

VLAD over a map's own local features finds a frame among same-date tiles, but across dates the
local features of farmland change too much for it (near chance on NAIP). The shipped
correction trunk (:mod:`orthonav.models.trunks`) was trained to correlate the same ground
across NAIP dates; its dense features, pooled over the valid cells of an image, describe a tile
or a north-up frame as one vector. A small head on top (1x1 conv, GeM pooling, linear
projection, L2 normalisation) is trained on triplets of our own data only: a frame-like view of
some ground in one year (a rotated footprint mask), its positive the tile-like square around
that ground in another year, its negatives the tiles of other ground in the batch (an InfoNCE
loss over all of them). The trunk stays frozen, so its features are computed once per year
image and training takes a few minutes on a CPU. Nothing is downloaded.

The model file holds trunk and head (half precision) in one file that orthonav ships
(``models/retrieval_naip.pt``, with a ``.json`` beside it recording data and scores).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from tqdm import tqdm

from orthonav.atomic import write_json_atomic
from orthonav.errors import OrthonavError
from orthonav.geo import GeoRaster
from orthonav.models.trunks import (
    DenseFeatures,
    load_model,
    read_model_file,
    to_tensor,
    valid_cells,
    write_model_file,
)

MODEL_FORMAT = "orthonav-retrieval-model"
MODEL_VERSION = 1


class RetrievalNet(nn.Module):
    """Gray image (H, W) + valid mask -> unit descriptor (dim,): frozen trunk, GeM, small MLP."""

    def __init__(self, trunk: DenseFeatures, dim: int = 128, hidden: int = 256) -> None:
        super().__init__()
        self.trunk = trunk.eval().requires_grad_(False)
        self.dim, self.hidden = dim, hidden
        self.gem_p = nn.Parameter(torch.tensor(3.0))
        self.project = nn.Sequential(nn.Linear(_channels(trunk), hidden), nn.ReLU(), nn.Linear(hidden, dim))

    def pool(self, features: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Trunk features (B, C, h, w) and valid cells (B, 1, h, w) -> (B, dim) unit vectors.

        GeM (generalised mean, learned exponent) over the valid cells only: a frame's warped
        footprint is a rotated rectangle, a tile at the map's edge is partly empty.
        """
        p = self.gem_p.clamp(1.0, 8.0)
        # 1e-4 ** 8 is still a normal float32: denormals would slow a CPU a hundredfold.
        x = features.clamp_min(1e-4).pow(p) * valid
        mean = x.flatten(2).sum(2) / valid.flatten(2).sum(2).clamp_min(1.0)
        return F.normalize(self.project(mean.pow(1.0 / p)), dim=1)

    def describe(self, gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """One image (uint8 gray, mask > 0 where it holds imagery) -> (dim,) float32 unit vector."""
        with torch.inference_mode():
            features = self.trunk(gray_tensor(gray, mask)[None])
            valid = valid_cells(torch.from_numpy(mask > 0)[None, None], tuple(features.shape[2:]))
            if not valid.any():
                return np.zeros(self.dim, np.float32)
            return self.pool(features, valid)[0].numpy().astype(np.float32)


def _channels(trunk: DenseFeatures) -> int:
    with torch.inference_mode():
        return int(trunk(torch.zeros(1, 3, 64, 64)).shape[1])


def gray_tensor(gray: np.ndarray, mask: np.ndarray | None = None) -> torch.Tensor:
    """Gray (the localizer's warped frame, a map tile read as gray) as the trunk's 3-channel input."""
    return to_tensor(np.repeat(gray[:, :, None], 3, axis=2), None if mask is None else mask > 0)


# --- model files ------------------------------------------------------------------------------


def save_retrieval_model(net: RetrievalNet, path: Path, info: dict) -> None:
    """Trunk and head in one file, written atomically."""
    fields = {"backbone": net.trunk.backbone, "stage": net.trunk.stage, "dim": net.dim, "hidden": net.hidden}
    write_model_file(path, MODEL_FORMAT, MODEL_VERSION, net, fields, info)


def load_retrieval_model(path: str | Path) -> tuple[RetrievalNet, dict]:
    """A retrieval model file -> (network in eval mode, its info); clear errors for wrong files."""
    payload = read_model_file(
        path, MODEL_FORMAT, MODEL_VERSION, "retrieval model", "orthonav map train-index"
    )
    trunk = DenseFeatures(payload["backbone"], payload["stage"])
    net = RetrievalNet(trunk, payload["dim"], payload["hidden"])
    try:
        net.load_state_dict(payload["state_dict"])
    except RuntimeError as exc:
        raise OrthonavError(f"{path}: its weights do not fit the recorded network ({exc})") from None
    return net.eval(), dict(payload.get("info", {}))


# --- training ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class RetrievalTrainConfig:
    """Sampling and optimisation; recorded in the model file. Sizes are in work px (source px)."""

    footprint_px: tuple[int, int] = (231, 173)  # the camera's ground footprint (640x480, 60 deg, 1000 m, 5 m)
    tile_px: int = 346  # the map's tiles at that altitude (1.5 x the footprint)
    scale_jitter: float = 0.3  # footprint and tile sizes vary by this much (other altitudes)
    area: tuple[float, float] = (0.0, 0.5)  # training ground: this fraction of each image's width
    steps: int = 400
    batch: int = 64
    temperature: float = 0.07
    lr: float = 3e-3
    negative_px: float = 150.0  # closer centres than this are not negatives
    seed: int = 0


@dataclass
class _YearFeatures:
    """Trunk features of one year image (and of its mirror image), computed once."""

    plain: torch.Tensor  # (C, h, w)
    mirrored: torch.Tensor


def year_features(trunk: DenseFeatures, path: Path) -> _YearFeatures:
    """One year's orthophoto as gray, through the frozen trunk, plain and mirrored left-right."""
    with GeoRaster(path) as raster:
        gray = cv2.cvtColor(raster.read_rgb(), cv2.COLOR_RGB2GRAY)
    with torch.no_grad():  # not inference_mode: the head trains on these
        plain = trunk(gray_tensor(gray)[None])[0]
        mirrored = trunk(gray_tensor(np.ascontiguousarray(gray[:, ::-1]))[None])[0]
    return _YearFeatures(plain, mirrored)


def train_retrieval(
    trunk: DenseFeatures, years: list[Path], config: RetrievalTrainConfig, progress: bool = True
) -> tuple[RetrievalNet, list[float]]:
    """Train the head on ``years`` (co-registered dates of one area); returns it and the losses."""
    if len(years) < 2:
        raise OrthonavError(f"retrieval training: needs at least two dates of one area, got {len(years)}")
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    features = [year_features(trunk, path) for path in years]
    net = RetrievalNet(trunk)
    optimizer = torch.optim.AdamW([p for p in net.parameters() if p.requires_grad], lr=config.lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=config.steps)
    losses = []
    for _ in tqdm(range(config.steps), desc="retrieval training", disable=not progress):
        frames, tiles, centres = _batch(features, trunk.stride, config, rng)
        anchors = torch.cat([net.pool(f[None], v[None]) for f, v in frames])
        positives = torch.cat([net.pool(f[None], v[None]) for f, v in tiles])
        loss = _contrastive_loss(anchors, positives, centres, config)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
        losses.append(float(loss.detach()))
    return net.eval(), losses


def _contrastive_loss(
    anchors: torch.Tensor, positives: torch.Tensor, centres: np.ndarray, config: RetrievalTrainConfig
) -> torch.Tensor:
    """Each frame against every tile of the batch: its own (same ground, another year) must win
    over the tiles of other ground (InfoNCE; tiles too close to the frame are left out)."""
    scores = anchors @ positives.T / config.temperature
    near = np.linalg.norm(centres[:, None] - centres[None], axis=2) <= config.negative_px
    np.fill_diagonal(near, False)
    scores = scores.masked_fill(torch.from_numpy(near), float("-inf"))
    return F.cross_entropy(scores, torch.arange(len(anchors)))


def _batch(
    features: list[_YearFeatures], stride: int, config: RetrievalTrainConfig, rng: np.random.Generator
) -> tuple[list, list, np.ndarray]:
    """Frame-like views (rotated footprint mask) of one year and their tiles in another year."""
    _, h, w = features[0].plain.shape
    frames, tiles, centres = [], [], []
    for _ in range(config.batch):
        first, second = rng.choice(len(features), 2, replace=False)
        mirror = bool(rng.integers(2))
        scale = rng.uniform(1.0 - config.scale_jitter, 1.0 + config.scale_jitter)
        tile_cells = max(4, round(config.tile_px * scale / stride))
        # The frame's centre anywhere within the middle half of its tile, like a map's overlapping tiles.
        x0 = int(rng.integers(round(config.area[0] * w), max(1, round(config.area[1] * w) - tile_cells)))
        y0 = int(rng.integers(0, h - tile_cells))
        cx = x0 + tile_cells * rng.uniform(0.25, 0.75)
        cy = y0 + tile_cells * rng.uniform(0.25, 0.75)
        frames.append(_frame_view(_pick(features[first], mirror), cx, cy, scale, stride, config, rng))
        tile = _pick(features[second], mirror)[:, y0 : y0 + tile_cells, x0 : x0 + tile_cells]
        tiles.append((tile, torch.ones(1, *tile.shape[1:])))
        centres.append((cx * stride, cy * stride))
    return frames, tiles, np.array(centres)


def _pick(year: _YearFeatures, mirror: bool) -> torch.Tensor:
    return year.mirrored if mirror else year.plain


def _frame_view(
    features: torch.Tensor,
    cx: float,
    cy: float,
    scale: float,
    stride: int,
    config: RetrievalTrainConfig,
    rng: np.random.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The cells a north-up frame at any heading covers: its footprint as a rotated rectangle."""
    fw, fh = (s * scale / stride for s in config.footprint_px)
    half = math.ceil(math.hypot(fw, fh) / 2)
    _, h, w = features.shape
    c0, r0 = int(np.clip(round(cx) - half, 0, w - 1)), int(np.clip(round(cy) - half, 0, h - 1))
    c1, r1 = min(w, round(cx) + half), min(h, round(cy) + half)
    box = cv2.boxPoints(((cx - c0, cy - r0), (fw, fh), float(rng.uniform(0.0, 360.0))))
    mask = np.zeros((r1 - r0, c1 - c0), np.uint8)
    cv2.fillConvexPoly(mask, np.round(box).astype(np.int32), 1)
    return features[:, r0:r1, c0:c1], torch.from_numpy(mask[None]).float()


def train_retrieval_model(
    years: list[Path], out: Path, config: RetrievalTrainConfig, trunk_file: Path, command: str = ""
) -> dict:
    """Train the head on the trunk of ``trunk_file``; write ``out`` and its ``.json`` record."""
    trunk, trunk_info = load_model(trunk_file)
    started = time.perf_counter()
    net, losses = train_retrieval(trunk, years, config)
    info = {
        "model": out.name,
        "architecture": f"frozen {trunk.backbone} trunk cut at stage {trunk.stage} ({trunk_file.name}), "
        f"GeM over valid cells, MLP {net.hidden} -> {net.dim}, L2-normalised; fp16 weights",
        "trained_from": "scratch head on the shipped correction trunk (no pretrained or downloaded weights)",
        "command": command,
        "training_dates": [p.name for p in years],
        "train_config": asdict(config),
        "train_seconds": round(time.perf_counter() - started, 1),
        "loss_first_last_20": [round(float(np.mean(losses[:20])), 3), round(float(np.mean(losses[-20:])), 3)],
        "trunk_info_model": trunk_info.get("model", trunk_file.name),
    }
    save_retrieval_model(net, out, info)
    write_json_atomic(out.with_suffix(".json"), info)
    return info
