"""Tile layout of a map: square tiles sized from the camera footprint, with overlap.

The map is matched at a *work* resolution: the coarser of the orthophoto's ground sample
distance and the camera's at the nominal altitude. Nothing finer than the camera can
resolve is useful, and coarser work pixels make extraction and matching cheaper.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError

# A frame seen at the map's resolution must span at least this many pixels (its short side)
# to carry enough texture to match: below it the geometry, not the imagery, is the problem.
MIN_FOOTPRINT_PX = 32


@dataclass(frozen=True)
class TilingConfig:
    """How a map is cut: nominal flight altitude, tile enlargement and overlap."""

    nominal_alt_m: float = 300.0
    scale_coef: float = 1.5
    overlap: float = 0.5
    # A frame is matched at most this many pixels across (its longer side, at the nominal
    # altitude): a fine map is tiled coarser, so that the cost follows a budget of pixels, not the
    # orthophoto's resolution (a 1600 px photo over a 5 cm map). 0: the camera's own resolution;
    # None: the backend's budget (``FeatureBackend.frame_budget_px``), set when the map is built.
    max_frame_px: int | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.nominal_alt_m) and 1.0 <= self.nominal_alt_m <= 20_000.0):
            raise OrthonavError(f"nominal altitude: expected 1..20000 m, got {self.nominal_alt_m}")
        if not (math.isfinite(self.scale_coef) and 1.0 <= self.scale_coef <= 10.0):
            raise OrthonavError(f"tile scale coefficient: expected 1..10, got {self.scale_coef}")
        if not (math.isfinite(self.overlap) and 0.0 <= self.overlap <= 0.9):
            raise OrthonavError(f"tile overlap: expected a fraction 0..0.9, got {self.overlap}")
        check_max_frame_px(self.max_frame_px, "max frame size")

    def for_backend(self, budget_px: int) -> TilingConfig:
        """This config with the backend's frame size budget where it sets none."""
        return self if self.max_frame_px is not None else replace(self, max_frame_px=budget_px)

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class TileLayout:
    """Tile boxes in work pixels: (col0, row0, col1, row1), end-exclusive, row-major order."""

    tile_px: int
    stride_px: int
    rows: int
    cols: int
    boxes: np.ndarray
    padded: np.ndarray

    def __len__(self) -> int:
        return len(self.boxes)


def check_max_frame_px(value: int | None, what: str) -> None:
    """A frame size budget (``TilingConfig.max_frame_px``; None: the backend's) or a clear error
    naming ``what``: the benches check theirs when configured, not when they first build a map."""
    if value is not None and value != 0 and not 64 <= value <= 8192:
        raise OrthonavError(f"{what}: expected 64..8192 px (or 0: no limit), got {value}")


def work_gsd_m(source_gsd_m: float, camera: Camera, config: TilingConfig) -> float:
    """Ground resolution at which the map is tiled and matched: the orthophoto's, the camera's at
    the nominal altitude, or coarser where the frame would be more than ``max_frame_px`` across."""
    if config.max_frame_px is None:
        raise OrthonavError("tiling: the frame size budget is unset (TilingConfig.for_backend sets it)")
    camera_gsd_m = camera.nadir_gsd_m(config.nominal_alt_m)
    if config.max_frame_px:
        camera_gsd_m *= max(1.0, max(camera.width, camera.height) / config.max_frame_px)
    return max(source_gsd_m, camera_gsd_m)


def layout_tiles(
    width_px: int, height_px: int, gsd_m: float, camera: Camera, config: TilingConfig
) -> TileLayout:
    """Cover a ``width_px`` x ``height_px`` work grid with overlapping square tiles."""
    foot_w, foot_h = camera.nadir_footprint_m(config.nominal_alt_m)
    tile_px = max(32, round(max(foot_w, foot_h) * config.scale_coef / gsd_m))
    stride = max(8, round(tile_px * (1.0 - config.overlap)))
    cols = _count(width_px, tile_px, stride)
    rows = _count(height_px, tile_px, stride)
    c0 = np.arange(cols) * stride
    r0 = np.arange(rows) * stride
    rr, cc = np.meshgrid(r0, c0, indexing="ij")
    boxes = np.stack([cc.ravel(), rr.ravel(), cc.ravel() + tile_px, rr.ravel() + tile_px], 1)
    padded = (boxes[:, 2] > width_px) | (boxes[:, 3] > height_px)
    return TileLayout(tile_px, stride, rows, cols, boxes.astype(np.int64), padded)


def _count(size: int, tile: int, stride: int) -> int:
    """Tiles needed along one axis so the last tile reaches the edge."""
    if size <= tile:
        return 1
    return 1 + math.ceil((size - tile) / stride)


def check_footprint(short_side_m: float, gsd_m: float, alt_m: float, what: str) -> None:
    """Refuse an altitude at which a frame covers too few map pixels to be matched, naming the
    altitude that would do."""
    span_px = short_side_m / gsd_m
    if span_px < MIN_FOOTPRINT_PX:
        needed = alt_m * MIN_FOOTPRINT_PX / span_px
        raise OrthonavError(
            f"{what} {alt_m:g} m: a frame covers only {span_px:.0f} px ({short_side_m:.0f} m) of the "
            f"{gsd_m:.2f} m/px map, too few to match (need {MIN_FOOTPRINT_PX} px): fly at least "
            f"{needed:.0f} m high, or use a finer orthophoto"
        )
