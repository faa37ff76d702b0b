"""Pictures of corrections and of their training."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.patches import Polygon

from orthonav.viz.axes import save_figure


def feature_rgb(*maps: np.ndarray) -> list[np.ndarray]:
    """(C, h, w) feature maps -> (h, w, 3) pictures of their first three principal components.

    One projection and one colour scale for all maps, so equal colours mean similar features.
    """
    c = maps[0].shape[0]
    flats = [m.reshape(c, -1).T.astype(np.float64) for m in maps]
    joint = np.concatenate(flats)
    mean = joint.mean(axis=0)
    if c >= 3:
        _, _, vt = np.linalg.svd((joint - mean)[:: max(1, len(joint) // 4000)], full_matrices=False)
        basis = vt[:3].T
    else:
        basis = np.repeat(np.eye(c)[:, :1], 3, axis=1)
    projected = [(f - mean) @ basis for f in flats]
    lo, hi = np.percentile(np.concatenate(projected), [2, 98], axis=0)
    return [
        np.clip((p - lo) / np.maximum(hi - lo, 1e-9), 0, 1).reshape(*m.shape[1:], 3)
        for p, m in zip(projected, maps, strict=True)
    ]


def plot_correction(
    correction,
    feature_maps: tuple[np.ndarray, np.ndarray],
    out: Path,
    truth_offset_px: tuple[float, float] | None = None,
) -> Path:
    """Frame view, region view with the found (and true) placement, heatmap, feature maps."""
    views, fix = correction.views, correction.fix
    frame_w, frame_h = views.geometry.frame_size
    region_w, region_h = views.geometry.region_size
    fig, axes = plt.subplots(2, 3, figsize=(15, 9))
    axes[0, 0].imshow(views.frame)
    axes[0, 0].set_title(f"camera frame, heading-up, {views.geometry.gsd_m:.2f} m/px")
    axes[0, 1].imshow(views.region)
    _outline(axes[0, 1], (region_w / 2, region_h / 2), (frame_w, frame_h), "white", "--", "prior")
    found = (correction.alignment.centre_x, correction.alignment.centre_y)
    _outline(axes[0, 1], found, (frame_w, frame_h), "red" if fix.accepted else "grey", "-", "found")
    if truth_offset_px is not None:
        truth = (region_w / 2 + truth_offset_px[0], region_h / 2 + truth_offset_px[1])
        _outline(axes[0, 1], truth, (frame_w, frame_h), "lime", ":", "truth")
    axes[0, 1].legend(loc="lower right", fontsize=8)
    axes[0, 1].set_title("map search region (lambda x footprint)")
    image = axes[0, 2].imshow(correction.heatmap.values, cmap="magma")
    axes[0, 2].plot(correction.peak.col, correction.peak.row, "c+", markersize=14)
    fig.colorbar(image, ax=axes[0, 2], shrink=0.8)
    axes[0, 2].set_title(
        f"heatmap (stride {correction.heatmap.stride}), peak ratio {correction.peak.ratio:.2f}"
    )
    frame_rgb, region_rgb = feature_rgb(*feature_maps)
    axes[1, 0].imshow(frame_rgb)
    axes[1, 0].set_title("frame features (3 principal components)")
    axes[1, 1].imshow(region_rgb)
    axes[1, 1].set_title("region features (same projection)")
    axes[1, 2].axis("off")
    axes[1, 2].text(0, 1, _summary(correction), va="top", family="monospace", fontsize=9)
    for ax in axes.flat[:5]:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{fix.method}: {'accepted' if fix.accepted else 'REJECTED: ' + fix.reason}")
    return save_figure(fig, out)


def _outline(
    ax, centre: tuple[float, float], size: tuple[int, int], colour: str, style: str, label: str
) -> None:
    (cx, cy), (w, h) = centre, size
    corners = np.array(
        [
            [cx - w / 2, cy - h / 2],
            [cx + w / 2, cy - h / 2],
            [cx + w / 2, cy + h / 2],
            [cx - w / 2, cy + h / 2],
        ]
    )
    ax.add_patch(Polygon(corners, fill=False, edgecolor=colour, linestyle=style, linewidth=1.5, label=label))


def _summary(correction) -> str:
    fix = correction.fix
    lines = [f"{k}: {v:.3f}" for k, v in fix.quality.items()]
    lines += [f"{k}: {v:.1f}" for k, v in fix.timings_ms.items()]
    if fix.accepted:
        lines += [f"lat, lon: {fix.pose.lat:.6f}, {fix.pose.lon:.6f}", f"sigma: {fix.sigma_m:.1f} m"]
    return "\n".join(lines)


def plot_training(history: list[dict], out: Path) -> Path:
    """Train and validation triplet loss per epoch, and validation top-1 placement accuracy."""
    epochs = [h["epoch"] for h in history]
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    left.plot(epochs, [h["train_loss"] for h in history], "o-", label="train")
    left.plot(epochs, [h["val_loss"] for h in history], "s-", label="validation")
    left.set_xlabel("epoch")
    left.set_ylabel("triplet loss")
    left.legend()
    right.plot(epochs, [h["val_top1"] for h in history], "o-", color="tab:green")
    right.set_xlabel("epoch")
    right.set_ylabel("validation: peak at the true placement")
    right.set_ylim(0, 1)
    for ax in (left, right):
        ax.grid(alpha=0.3)
    fig.suptitle("correction trunk training")
    return save_figure(fig, out)


def plot_triplets(anchors: list[np.ndarray], rows: dict[str, list[np.ndarray]], out: Path) -> Path:
    """Columns = samples; first row the anchors, then one row per kind of patch."""
    n = len(anchors)
    fig, axes = plt.subplots(1 + len(rows), n, figsize=(2.6 * n, 2.2 * (1 + len(rows))), squeeze=False)
    for j in range(n):
        axes[0, j].imshow(anchors[j])
        for i, (name, patches) in enumerate(rows.items(), start=1):
            axes[i, j].imshow(patches[j])
            if j == 0:
                axes[i, j].set_ylabel(name)
    axes[0, 0].set_ylabel("anchor")
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    return save_figure(fig, out)


def plot_route(raster, frame, tracks: dict[str, np.ndarray], out: Path) -> Path:
    """Tracks (1 s samples, ENU metres in ``frame``, a LocalFrame; one is "truth") over the
    orthophoto ``raster``, and each track's distance from the truth over time."""
    scale = max(raster.width, raster.height) / 1024.0
    shape = (max(1, round(raster.height / scale)), max(1, round(raster.width / scale)))
    fig, (ax, right) = plt.subplots(1, 2, figsize=(16, 7), gridspec_kw={"width_ratios": [1.2, 1]})
    ax.imshow(raster.read_rgb(out_shape=shape), extent=(0, raster.width, raster.height, 0))
    fixed = {"truth": ("lime", "-"), "INS alone": ("red", "--")}
    others = ["tab:blue", "tab:orange", "tab:purple", "tab:brown", "tab:pink", "tab:cyan", "tab:olive"]
    colours = iter(others * len(tracks))
    truth = tracks["truth"]
    for label, track in tracks.items():
        colour, style = fixed[label] if label in fixed else (next(colours), "-")
        col, row = raster.latlon_to_pixel(*frame.to_latlon(track[:, 0], track[:, 1]))
        ax.plot(col, row, style, color=colour, linewidth=1.6, label=label)
        if label != "truth":
            right.plot(np.hypot(*(track - truth).T), style, color=colour, label=label)
    ax.legend(loc="lower right", fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])
    ax.set_title("route over the map")
    right.set_xlabel("time (s)")
    right.set_ylabel("distance from the true position (m)")
    right.grid(alpha=0.3)
    right.legend(fontsize=8)
    right.set_title("INS alone vs corrected by the map")
    return save_figure(fig, out)
