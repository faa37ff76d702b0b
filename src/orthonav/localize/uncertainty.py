"""What a flat-ground pose cannot see, measured from its own inliers, for the fix's sigma.

Without a DSM the pose assumes the matched points lie on one plane. Where they do not (roofs
and trees at a fair share of the altitude), a free tilt absorbs the relief's trend across the
frame and moves the camera by about height x that tilt, and the fit's covariance does not know:
its points agree with the tilted plane about as well as with the right one. What the tilt cannot
absorb stays in the residuals: their excess over the matcher's noise, in metres on the ground,
measures the relief, and the tilt it leaves goes with it over the footprint's width.

An attitude prior holds the tilt: the relief then stays in the residuals instead of moving the
camera, and the fit's own covariance with the slope floor covers it. The gains were calibrated
on inliers over random boxes (houses, trees) seen from 30 m, and checked on other scenes, other
lenses and on real photos over flat farmland (docs/benchmarks/real.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from orthonav.camera import Camera, CameraPose, project_points


@dataclass(frozen=True)
class FlatGroundModel:
    """The flat-ground allowance: ``slope`` x height (the relief no image shows: a gentle, even
    slope), or, where larger, the residuals' excess over ``noise_px`` (the matcher's own
    per-coordinate error) in metres x height / footprint width x ``free_gain`` (tilt free) or
    ``held_gain`` (tilt held by an attitude prior)."""

    slope: float = 0.03
    free_gain: float = 9.0
    held_gain: float = 1.0
    noise_px: float = 1.0

    def sigma_m(self, camera: Camera, cam: CameraPose, residual_m: float, tilt_held: bool) -> float:
        height_m = cam.alt_agl_m
        gain = self.held_gain if tilt_held else self.free_gain
        width_m = camera.nadir_footprint_m(height_m)[0]
        return max(self.slope * height_m, gain * residual_m * height_m / width_m)


def unexplained_m(
    camera: Camera, frame_px: np.ndarray, ground_en: np.ndarray, cam: CameraPose, noise_px: float
) -> float:
    """The flat-ground pose's per-coordinate residual beyond ``noise_px``, in metres on the ground
    (frame px <-> (N, 2) ground): the relief the plane could not absorb."""
    residual = project_points(camera, cam, ground_en) - frame_px
    rms_px = float(np.sqrt(np.mean(residual**2)))
    return math.sqrt(max(0.0, rms_px**2 - noise_px**2)) * cam.alt_agl_m / camera.fx
