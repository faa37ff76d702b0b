"""Triplet-loss training of a correction trunk, resumable, with loss curves.

For L2-normalised feature maps, |Fa - Fx|^2 averaged over locations is 2 - 2 * (mean cosine),
so the triplet loss max(|Fa - Fp|^2 - |Fa - Fn|^2 + margin, 0) asks exactly that the
correlation heatmap be higher at the true placement than at a shifted one. One correlation
of the anchor over its region scores the positive and every shifted negative at once.

Negatives per anchor (``mining``):
- ``triplets``: ``negatives`` random shifted placements plus the temporal one;
- ``batch-hard``: the hardest placement outside the positive's neighbourhood, plus the
  temporal one.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from orthonav.atomic import atomic_path, write_text_atomic
from orthonav.errors import OrthonavError
from orthonav.frames import Photometric
from orthonav.models.dataset import TripletConfig, TripletSet, year_pair_triplets
from orthonav.models.trunks import DenseFeatures, correlate, save_model, to_tensor, valid_cells

CHECKPOINT = "checkpoint.pt"
MODEL = "model.pt"
HISTORY = "history.json"
MININGS = ("triplets", "batch-hard")


@dataclass(frozen=True)
class TrainConfig:
    backbone: str = "resnet18"
    stage: int = 2
    epochs: int = 10
    batch: int = 16
    lr: float = 1e-3
    weight_decay: float = 1e-4
    margin: float = 0.3
    mining: str = "batch-hard"
    negatives: int = 8
    exclusion_cells: float = 1.5
    seed: int = 0

    def __post_init__(self) -> None:
        if self.mining not in MININGS:
            raise OrthonavError(f"training mining {self.mining!r}: expected one of {', '.join(MININGS)}")
        if self.epochs < 1 or self.batch < 1 or self.lr <= 0 or self.margin <= 0:
            raise OrthonavError("training: expected epochs >= 1, batch >= 1, lr > 0 and margin > 0")


def train(
    train_set: TripletSet,
    val_set: TripletSet,
    config: TrainConfig,
    out_dir: Path,
    info: dict | None = None,
    progress: bool = True,
) -> dict:
    """Train (or resume) in ``out_dir``; the best model by validation accuracy is ``model.pt``.

    ``info`` (data, command) is recorded in the model file and ``history.json``.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    net = DenseFeatures(config.backbone, config.stage)
    optimizer = torch.optim.AdamW(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=config.epochs)
    state = _resume(out_dir / CHECKPOINT, config, net, optimizer, schedule)
    history, best = state["history"], state["best"]
    rng = np.random.default_rng([config.seed, len(history)])
    for epoch in range(len(history), config.epochs):
        t0 = time.perf_counter()
        loss = _epoch(net, train_set, config, optimizer, rng, progress, f"epoch {epoch + 1}/{config.epochs}")
        schedule.step()
        scores = evaluate(net, val_set, config)
        history.append(
            {"epoch": epoch + 1, "train_loss": loss, **scores, "seconds": time.perf_counter() - t0}
        )
        if scores["val_top1"] >= best:
            best = scores["val_top1"]
            record = {**(info or {}), "train": asdict(config), "epoch": epoch + 1, "validation": scores}
            save_model(net, out_dir / MODEL, record)
        _checkpoint(out_dir / CHECKPOINT, config, net, optimizer, schedule, history, best)
        write_text_atomic(
            out_dir / HISTORY,
            json.dumps({"config": asdict(config), "info": info, "history": history}, indent=2),
        )
    return {"history": history, "best_val_top1": best, "model": str(out_dir / MODEL)}


def evaluate(net: DenseFeatures, data: TripletSet, config: TrainConfig) -> dict[str, float]:
    """Validation loss, and how often the heatmap's maximum is the true placement (top-1)."""
    net.eval()
    losses, hits, errors = [], [], []
    with torch.inference_mode():
        for start in range(0, len(data), config.batch):
            index = np.arange(start, min(start + config.batch, len(data)))
            heat, pos, temporal = _heatmaps(net, data, index, flips=None)
            losses.append(float(_loss(heat, pos, temporal, config, None)) * len(index))
            flat = heat.flatten(1).argmax(dim=1)
            rows, cols = flat // heat.shape[2], flat % heat.shape[2]
            err = torch.hypot((rows - pos[0]).float(), (cols - pos[1]).float())
            hits += (err == 0).tolist()
            errors += err.tolist()
    return {
        "val_loss": sum(losses) / len(data),
        "val_top1": float(np.mean(hits)),
        "val_mean_cell_error": float(np.mean(errors)),
    }


def _epoch(
    net: DenseFeatures,
    data: TripletSet,
    config: TrainConfig,
    optimizer: torch.optim.Optimizer,
    rng: np.random.Generator,
    progress: bool,
    label: str,
) -> float:
    net.train()
    order = rng.permutation(len(data))
    batches = [order[i : i + config.batch] for i in range(0, len(order), config.batch)]
    total = 0.0
    for index in tqdm(batches, desc=label, disable=not progress, leave=False):
        flips = rng.integers(0, 2, size=2).astype(bool)
        heat, pos, temporal = _heatmaps(net, data, index, flips=flips, rng=rng)
        loss = _loss(heat, pos, temporal, config, rng)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        total += float(loss.detach()) * len(index)
    return total / len(data)


def _heatmaps(
    net: DenseFeatures,
    data: TripletSet,
    index: np.ndarray,
    flips: np.ndarray | None,
    rng: np.random.Generator | None = None,
) -> tuple[torch.Tensor, tuple[int, int], torch.Tensor]:
    """Correlation heatmaps (B, rows, cols) over each region cut to whole cells around the
    positive; the positive's cell (row, col); each temporal negative's cell (B, 2) (row, col)."""
    s = net.stride
    h, w = data.anchors.shape[1:3]
    mx, my = data.margin_px
    cx, cy = (mx // s) * s, (my // s) * s  # margins that are whole cells
    anchors, masks, regions = [], [], []
    for i in index:
        anchor, mask = data.anchors[i], data.anchor_masks[i]
        region = data.regions[i, my - cy : my + h + cy, mx - cx : mx + w + cx]
        if rng is not None:
            anchor = _photometric(anchor, rng)
        anchors.append(to_tensor(anchor, mask))
        masks.append(torch.from_numpy(mask))
        regions.append(to_tensor(region, None))
    a, r, m = torch.stack(anchors), torch.stack(regions), torch.stack(masks)[:, None].float()
    temporal = torch.from_numpy(np.round(data.temporal_px[index] / s)).long()  # (B, 2) (x, y) cells
    if flips is not None:
        dims = [d for d, flip in zip((3, 2), flips, strict=True) if flip]
        if dims:  # flipping anchor and region alike keeps the positive centred
            a, r, m = a.flip(dims), r.flip(dims), m.flip(dims)
            temporal = temporal * torch.tensor([-1 if flips[0] else 1, -1 if flips[1] else 1])
    fa, fr = net(a), net(r)
    valid = valid_cells(m, tuple(fa.shape[2:]))
    heat = correlate(fr, fa, valid)
    pos = (cy // s, cx // s)
    temporal_cells = torch.stack([temporal[:, 1] + pos[0], temporal[:, 0] + pos[1]], dim=1)
    return heat, pos, temporal_cells


def _loss(
    heat: torch.Tensor,
    pos: tuple[int, int],
    temporal: torch.Tensor,
    config: TrainConfig,
    rng: np.random.Generator | None,
) -> torch.Tensor:
    """Mean triplet loss; distances d = 2 - 2 * heat (squared L2 of unit feature maps)."""
    b, rows, cols = heat.shape
    dist = 2.0 - 2.0 * heat
    d_pos = dist[:, pos[0], pos[1]]
    rr, cc = torch.meshgrid(torch.arange(rows), torch.arange(cols), indexing="ij")
    far = torch.hypot((rr - pos[0]).float(), (cc - pos[1]).float()) > config.exclusion_cells
    if config.mining == "batch-hard":
        d_neg = dist.masked_fill(~far, math.inf).flatten(1).min(dim=1).values[:, None]
    else:
        choices = torch.nonzero(far.flatten()).flatten()
        gen = rng or np.random.default_rng(0)
        picks = choices[torch.from_numpy(gen.integers(0, len(choices), size=(b, config.negatives)))]
        d_neg = torch.gather(dist.flatten(1), 1, picks)
    inside = (temporal[:, 0] >= 0) & (temporal[:, 0] < rows) & (temporal[:, 1] >= 0) & (temporal[:, 1] < cols)
    t_rows, t_cols = temporal[:, 0].clamp(0, rows - 1), temporal[:, 1].clamp(0, cols - 1)
    d_temporal = dist[torch.arange(b), t_rows, t_cols]
    losses = F.relu(d_pos[:, None] - d_neg + config.margin).mean(dim=1)
    losses = losses + F.relu(d_pos - d_temporal + config.margin) * inside.float()
    return losses.mean()


def _photometric(rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Blur, brightness/contrast and noise on the anchor (flips are applied to whole batches)."""
    bgr = Photometric.random(rng, 0.7).apply(np.ascontiguousarray(rgb[..., ::-1]), rng)
    return bgr[..., ::-1]


def _resume(path: Path, config: TrainConfig, net, optimizer, schedule) -> dict:
    if not path.is_file():
        return {"history": [], "best": -1.0}
    state = torch.load(path, map_location="cpu", weights_only=False)
    if state.get("config") != asdict(config):
        raise OrthonavError(
            f"{path}: a checkpoint of another training configuration; "
            "use a new --out folder or the same options"
        )
    net.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    schedule.load_state_dict(state["schedule"])
    return {"history": state["history"], "best": state["best"]}


def _checkpoint(
    path: Path, config: TrainConfig, net, optimizer, schedule, history: list, best: float
) -> None:
    state = {
        "config": asdict(config),
        "model": net.state_dict(),
        "optimizer": optimizer.state_dict(),
        "schedule": schedule.state_dict(),
        "history": history,
        "best": best,
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def dates_in(data_dir: Path, dates: list[str]) -> list[Path]:
    """The GeoTIFFs of ``data_dir`` whose names contain each date, one per date, or a clear error."""
    files = sorted(data_dir.glob("*.tif"))
    if not files:
        raise OrthonavError(f"{data_dir}: no GeoTIFFs (expected co-registered orthophotos of several dates)")
    chosen = []
    for date in dates:
        match = [f for f in files if date in f.stem]
        if len(match) != 1:
            raise OrthonavError(
                f"{data_dir}: {len(match)} files match date {date!r} (expected exactly one among "
                f"{', '.join(f.name for f in files)})"
            )
        chosen.append(match[0])
    return chosen


def train_on_dates(
    orthos: list[Path],
    triplets: TripletConfig,
    val_area: tuple[float, float],
    val_samples: int,
    config: TrainConfig,
    out_dir: Path,
    extra: TripletSet | None = None,
    info: dict | None = None,
    progress: bool = True,
) -> dict:
    """Build the area-split triplet sets from every pair of dates and train.

    ``extra`` (e.g. triplets from a real flight) joins the training set. The result carries
    ``preview`` (a few training triplets as image patches) for the caller to draw beside the
    training curves.
    """
    (lo, hi), (val_lo, val_hi) = triplets.area, val_area
    if val_lo < hi and lo < val_hi:
        raise OrthonavError(
            f"validation area {val_lo:g},{val_hi:g} overlaps the training area {lo:g},{hi:g}: "
            "validation must use map strips that are never trained on"
        )
    out_dir.mkdir(parents=True, exist_ok=True)
    train_set = year_pair_triplets(orthos, triplets, progress)
    val_set = year_pair_triplets(
        orthos, replace(triplets, area=val_area, samples=val_samples, seed=triplets.seed + 1), progress
    )
    if extra is not None:
        train_set = TripletSet.concatenate([train_set, extra])
    record = {
        **(info or {}),
        "dates": [p.name for p in orthos],
        "triplets": triplets.to_dict(),
        "val_area": list(val_area),
        "train_samples": len(train_set),
        "val_samples": len(val_set),
    }
    result = train(train_set, val_set, config, out_dir, record, progress)
    return {**result, "preview": preview_patches(train_set, 6)}


def preview_patches(data: TripletSet, n: int) -> dict[str, list[np.ndarray]]:
    """Anchor, positive, temporal and a nearby shifted negative for the first ``n`` samples."""
    mx, my = data.margin_px
    picks = range(min(n, len(data)))
    temporal = [np.clip(np.round(data.temporal_px[i]).astype(int), [-mx, -my], [mx, my]) for i in picks]
    return {
        "anchor": [data.anchors[i] for i in picks],
        "positive": [data.patch(i) for i in picks],
        "temporal negative": [data.patch(i, *t) for i, t in zip(picks, temporal, strict=True)],
        "shifted negative": [data.patch(i, mx // 2, -(my // 2)) for i in picks],
    }
