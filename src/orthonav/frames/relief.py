"""Frames of a scene with relief that the map's flat ground does not model: boxes (houses, tree
crowns) standing on the orthophoto's ground, seen in perspective from a low flight.

A true orthophoto shows every roof where it stands; a camera low above it sees the roofs
displaced away from the point under it by height / (altitude - height) of their distance,
and hides the ground behind them. The box tops carry the orthophoto's texture where they
stand (what a true orthophoto shows there), so only the parallax differs from a flat render:
the localizer's flat-ground model faces displacements it cannot explain, as over houses and
trees at a tenth to a third of the altitude.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from orthonav.camera import Camera, CameraPose, pixel_to_ground, project_ground
from orthonav.errors import OrthonavError
from orthonav.frames.render import Photometric, TruePose, render_frame
from orthonav.geo import GeoRaster

# Height resolution of the ray march (m) and the box grid's cell (m).
_STEP_M = 0.2
_CELL_M = 0.1


@dataclass(frozen=True)
class Relief:
    """Random boxes over a frame's footprint: heights in ``heights_m``, sides in ``sides_m``,
    together covering about ``cover`` of it."""

    heights_m: tuple[float, float] = (5.0, 10.0)
    sides_m: tuple[float, float] = (6.0, 15.0)
    cover: float = 0.35

    def __post_init__(self) -> None:
        if not 0.0 < self.heights_m[0] <= self.heights_m[1]:
            raise OrthonavError(f"relief heights {self.heights_m}: expected 0 < low <= high (m)")
        if not 0.0 < self.sides_m[0] <= self.sides_m[1]:
            raise OrthonavError(f"relief sides {self.sides_m}: expected 0 < low <= high (m)")
        if not 0.0 < self.cover < 1.0:
            raise OrthonavError(f"relief cover {self.cover}: expected a share between 0 and 1")

    def heights(self, half_extent_m: float, rng: np.random.Generator) -> np.ndarray:
        """A north-up grid of heights (m) over +-``half_extent_m`` around the drone, ``_CELL_M`` a
        cell, row 0 at the north edge."""
        size = math.ceil(2.0 * half_extent_m / _CELL_M)
        grid = np.zeros((size, size), np.float32)
        mean_side = float(np.mean(self.sides_m))
        boxes = max(1, round(self.cover * (2.0 * half_extent_m) ** 2 / mean_side**2))
        for _ in range(boxes):
            centre = rng.uniform(0, size, 2)
            sides = rng.uniform(*self.sides_m, 2) / _CELL_M
            rect = (tuple(centre), tuple(sides), float(rng.uniform(0, 180)))
            corners = cv2.boxPoints(rect).round().astype(np.int32)
            height = float(rng.uniform(*self.heights_m))
            box = np.zeros_like(grid)
            cv2.fillPoly(box, [corners], height)
            np.maximum(grid, box, out=grid)
        return grid


def render_relief_frame(
    raster: GeoRaster,
    camera: Camera,
    pose: TruePose,
    relief: Relief,
    photometric: Photometric | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """(H, W, 3) BGR frame of ``raster`` with ``relief``'s boxes, ``pose`` above the ground.

    Each pixel's ray is marched down from the tallest box to the ground; where it first meets a
    box (side or top) it takes the orthophoto's colour under that point, read from the flat
    render at the pixel that sees the point on the ground."""
    if camera.distortion and any(camera.distortion):
        raise OrthonavError("relief frames: expected a pinhole camera without distortion")
    rng = rng or np.random.default_rng(0)
    flat = render_frame(raster, camera, pose)
    cam_pose = CameraPose(0.0, 0.0, pose.alt_agl_m, pose.yaw_deg, pose.pitch_deg, pose.roll_deg)
    u, v = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    ground = pixel_to_ground(camera, cam_pose, np.column_stack([u.ravel(), v.ravel()]))
    half = float(np.abs(ground).max()) + 1.0
    grid = relief.heights(half, rng)
    hit = _ray_heights(ground, pose.alt_agl_m, grid, half, relief.heights_m[1])
    seen = ground * ((pose.alt_agl_m - hit) / pose.alt_agl_m)[:, None]
    px = project_ground(camera, cam_pose, seen).astype(np.float32) - 0.5
    shape = (camera.height, camera.width)
    frame = cv2.remap(flat, px[:, 0].reshape(shape), px[:, 1].reshape(shape), cv2.INTER_LINEAR)
    return photometric.apply(frame, rng) if photometric is not None else frame


def _ray_heights(ground: np.ndarray, alt_m: float, grid: np.ndarray, half: float, top_m: float) -> np.ndarray:
    """The height at which each pixel's ray (through ``ground`` on z = 0) first meets the grid's
    surface, marched down in ``_STEP_M`` steps; 0 where it reaches the ground."""
    hit = np.zeros(len(ground), np.float32)
    open_ = np.ones(len(ground), bool)
    for z in np.arange(top_m, 0.0, -_STEP_M):
        at = ground[open_] * ((alt_m - z) / alt_m)
        cols = np.clip(((at[:, 0] + half) / _CELL_M).astype(int), 0, grid.shape[1] - 1)
        rows = np.clip(((half - at[:, 1]) / _CELL_M).astype(int), 0, grid.shape[0] - 1)
        below = grid[rows, cols]
        meets = below >= z
        index = np.flatnonzero(open_)[meets]
        hit[index] = z
        open_[index] = False
    return hit
