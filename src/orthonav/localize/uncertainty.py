"""What a flat-ground pose cannot see, measured from its own inliers, for the fix's sigma.

Without a DSM the pose assumes the matched points lie on one plane. Where they do not (roofs
and trees at a fair share of the altitude), a free tilt absorbs the relief's trend across the
frame and moves the camera by about height x that tilt, and the fit's covariance does not know:
its points agree with the tilted plane about as well as with the right one. What the tilt cannot
absorb stays in the residuals: their excess over the matcher's noise, in metres on the ground,
measures the relief, and the tilt it leaves goes with it over the footprint's width.

An even slope of the ground is the one relief no image shows: the plane fits it exactly, with
the tilt and the camera moved by about height x the slope. With the tilt free, only a fixed
allowance covers it. An attitude prior holds the tilt, and the pose's position then moves with
its tilt's error alone (the image centre stays where the map puts it): by as far as the image
pulled the tilt from the prior, which is where a slope shows, and by the prior's own error. The
fit's covariance carries the latter only as far as it trusts the image's tilt, which relief can
bias towards the prior's by chance, so both join: height x their root sum of squares takes the
fixed allowance's place wherever it is the smaller. Relief beyond a plane stays in the residuals.

The gains were calibrated on inliers over random boxes (houses, trees) seen from 30 m, and
checked on other scenes, other lenses and on real photos over flat farmland
(docs/benchmarks/real.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from orthonav.camera import Camera, CameraPose, project_points


@dataclass(frozen=True)
class FlatGroundModel:
    """The flat-ground allowance: the unseen slope's (``slope`` x height; with the tilt held by
    an attitude prior, height x how far that tilt may be off where smaller), or, where larger,
    the residuals' excess over ``noise_px`` (the matcher's own per-coordinate error) in metres x
    height / footprint width x ``free_gain`` (tilt free) or ``held_gain`` (tilt held)."""

    slope: float = 0.03
    free_gain: float = 9.0
    held_gain: float = 1.0
    noise_px: float = 1.0

    def sigma_m(
        self, camera: Camera, cam: CameraPose, residual_m: float, held_off_deg: float | None
    ) -> float:
        """``held_off_deg``: how far roll and pitch held by an attitude prior may be off
        (:func:`held_tilt_deg`); None where the tilt was the image's own."""
        height_m = cam.alt_agl_m
        width_m = camera.nadir_footprint_m(height_m)[0]
        if held_off_deg is None:
            return max(self.slope * height_m, self.free_gain * residual_m * height_m / width_m)
        slope = min(self.slope, math.tan(math.radians(held_off_deg)))
        return max(slope * height_m, self.held_gain * residual_m * height_m / width_m)


def held_tilt_deg(pull_deg: float, prior_sigma_deg: float) -> float:
    """How far a tilt held by an attitude prior may be off: the image's pull from the prior
    (the angle between the fitted roll/pitch and the prior's) with the prior's own sigma."""
    return math.hypot(pull_deg, prior_sigma_deg)


def unexplained_m(
    camera: Camera, frame_px: np.ndarray, ground_en: np.ndarray, cam: CameraPose, noise_px: float
) -> float:
    """The flat-ground pose's per-coordinate residual beyond ``noise_px``, in metres on the ground
    (frame px <-> (N, 2) ground): the relief the plane could not absorb."""
    residual = project_points(camera, cam, ground_en) - frame_px
    rms_px = float(np.sqrt(np.mean(residual**2)))
    return math.sqrt(max(0.0, rms_px**2 - noise_px**2)) * cam.alt_agl_m / camera.fx
