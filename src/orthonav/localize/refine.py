"""Final alignment after the correlation peak: translation -> similarity by ECC.

A correlation heatmap only searches translations, so a heading error of a few degrees or an
altitude error of a few percent biases its peak by a pixel or two (the edges far from the
centre pull it). ECC (Evangelidis & Psarakis, OpenCV ``findTransformECC``) maximises the
correlation coefficient over an affine warp starting at the peak, on the same gradient
images, and so also measures the heading and scale (altitude) errors. It is an
inverse-compositional Lucas-Kanade relative, as in Goforth & Lucey's deep alignment.
A result that drifts away from the peak, or implies an implausible rotation or scale, is
discarded and the peak is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

ECC_ITERATIONS = 60
ECC_EPS = 1e-5
ECC_BLUR = 3


@dataclass(frozen=True)
class Alignment:
    """The frame view's place in the region view: centre (px), rotation and scale."""

    centre_x: float
    centre_y: float
    rotation_deg: float  # clockwise turn of the frame's content in the map (image y down)
    scale: float  # > 1: the frame covers more ground than the prior altitude says
    score: float


def ecc_align(
    frame_gradient: np.ndarray,
    frame_mask: np.ndarray,
    region_gradient: np.ndarray,
    region_mask: np.ndarray,
    placement: tuple[float, float],
    max_shift_px: float,
    max_rotation_deg: float,
    max_scale_change: float,
) -> Alignment | None:
    """Affine ECC of the views' gradient images (:func:`gradient_magnitude`, as the correlation
    made them) from the translation ``placement`` (frame top-left in region px), or None."""
    template = frame_gradient
    if not frame_mask.all():  # unseen pixels take the mean: no edges where the camera saw nothing
        template = frame_gradient.copy()
        template[~frame_mask] = float(template[frame_mask].mean())
    warp = np.array([[1.0, 0.0, placement[0]], [0.0, 1.0, placement[1]]], np.float32)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, ECC_ITERATIONS, ECC_EPS)
    try:
        mask = region_mask.astype(np.uint8)
        score, warp = cv2.findTransformECC(
            template, region_gradient, warp, cv2.MOTION_AFFINE, criteria, mask, ECC_BLUR
        )
    except cv2.error:  # "The algorithm stopped before its convergence": no alignment
        return None
    h, w = frame_gradient.shape[:2]
    centre = warp @ np.array([w / 2.0, h / 2.0, 1.0])
    start = np.array([placement[0] + w / 2.0, placement[1] + h / 2.0])
    linear = warp[:, :2].astype(float)
    det = float(np.linalg.det(linear))
    if det <= 0 or not np.all(np.isfinite(warp)):
        return None
    scale = math.sqrt(det)
    rotation = math.degrees(math.atan2(linear[1, 0] - linear[0, 1], linear[0, 0] + linear[1, 1]))
    singular = np.linalg.svd(linear, compute_uv=False)
    if (
        np.hypot(*(centre - start)) > max_shift_px
        or abs(rotation) > max_rotation_deg
        or abs(math.log(scale)) > math.log1p(max_scale_change)
        or singular[0] / singular[1] > 1.0 + max_scale_change
    ):
        return None
    return Alignment(float(centre[0]), float(centre[1]), rotation, scale, float(score))
