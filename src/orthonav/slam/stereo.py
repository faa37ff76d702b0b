"""Distance and size of objects from two UAVs: a stereo pair with a variable, measured baseline.

Two UAVs whose frames overlap by more than half form a stereo pair whose baseline is the
vector between them. It is not fixed: it is measured from the image of the other UAV, whose
size is known, in a camera of the first (range from the apparent span, direction from the
pixel). Over a flight the baseline varies; the frame pair used for an object is the one whose
measured baseline gives the smallest predicted distance error,
``e_d = sqrt((D^2 / (f B_across) sigma_disparity)^2 + (D sigma_B / B)^2)``, which weighs a
longer baseline (smaller disparity error) against its larger measurement error (sigma_B grows
as B^2); B_across is the baseline's part across the line of sight (the height difference of
two nadir cameras gives no parallax). The prediction is an expected error: the error of one
pair is dominated by that pair's random baseline error, which no prediction can know.

The sighting's apparent span is modelled as ``f * span_m / depth`` (a small object seen
broadside); attitudes come from the AHRS.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from orthonav.camera import Camera, CameraPose, footprint_enu
from orthonav.errors import OrthonavError
from orthonav.slam.association import overlap_fraction
from orthonav.slam.rig import RigCamera

MIN_STEREO_OVERLAP = 0.5


@dataclass(frozen=True)
class Sighting:
    """The other UAV in a frame: the centre of its image (px) and its apparent span (px)."""

    centre_px: tuple[float, float]
    span_px: float


@dataclass(frozen=True)
class Baseline:
    """The other UAV relative to this one's body (FRD metres), with its uncertainty."""

    vector_body_m: np.ndarray
    bearing_body: np.ndarray  # unit vector from the spotting camera
    range_m: float
    range_sigma_m: float
    bearing_sigma_rad: float


def baseline_from_sighting(
    spotter: RigCamera, sighting: Sighting, known_span_m: float, pixel_sigma_px: float = 0.5
) -> Baseline:
    """Range from the known span (depth = f S / s), bearing from the pixel, through the extrinsics."""
    cam = spotter.camera
    u, v = sighting.centre_px
    if not (0 <= u < cam.width and 0 <= v < cam.height):
        raise OrthonavError(
            f"sighting at ({u:.1f}, {v:.1f}) px is outside the {cam.width}x{cam.height} frame"
        )
    if not (math.isfinite(sighting.span_px) and sighting.span_px >= 2.0):
        raise OrthonavError(f"sighting span {sighting.span_px} px: the other UAV must span at least 2 px")
    if not (math.isfinite(known_span_m) and known_span_m > 0):
        raise OrthonavError(f"known UAV span: expected a positive size in metres, got {known_span_m}")
    f = math.sqrt(cam.fx * cam.fy)
    ray = np.array([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, 1.0])
    depth = f * known_span_m / sighting.span_px
    range_m = depth * float(np.linalg.norm(ray))
    bearing_cam = ray / np.linalg.norm(ray)
    bearing_body = spotter.body_r_camera @ bearing_cam
    vector = np.asarray(spotter.lever_arm_m) + range_m * bearing_body
    return Baseline(
        vector_body_m=vector,
        bearing_body=vector / np.linalg.norm(vector),
        range_m=float(np.linalg.norm(vector)),
        range_sigma_m=range_m * pixel_sigma_px * math.sqrt(2.0) / sighting.span_px,
        bearing_sigma_rad=pixel_sigma_px / f,
    )


@dataclass(frozen=True)
class StereoPair:
    """Two simultaneous frames and what is known of their geometry (ENU, the first at the origin)."""

    camera_a: Camera
    camera_b: Camera
    r_enu_cam_a: np.ndarray
    r_enu_cam_b: np.ndarray
    baseline_enu_m: np.ndarray  # camera b's centre minus camera a's
    baseline_sigma_m: float
    pixels_a: np.ndarray  # (N, 2) the same object points in both frames
    pixels_b: np.ndarray


def check_overlap(camera_a: Camera, pose_a: CameraPose, camera_b: Camera, pose_b: CameraPose) -> float:
    """The shared ground of two frames (over the smaller footprint); refuses less than half."""
    overlap = overlap_fraction(footprint_enu(camera_a, pose_a), footprint_enu(camera_b, pose_b))
    if overlap <= MIN_STEREO_OVERLAP:
        raise OrthonavError(
            f"two-UAV stereo: the frames share {100 * overlap:.0f} % of their ground; "
            f"more than {100 * MIN_STEREO_OVERLAP:.0f} % is needed"
        )
    return overlap


def triangulate(pair: StereoPair) -> np.ndarray:
    """(N, 3) object points in ENU metres relative to camera a (linear triangulation)."""
    if len(pair.pixels_a) == 0 or len(pair.pixels_a) != len(pair.pixels_b):
        raise OrthonavError("two-UAV stereo: expected the same non-empty set of points in both frames")
    r_a, r_b = pair.r_enu_cam_a.T, pair.r_enu_cam_b.T
    p_a = pair.camera_a.K @ np.column_stack([r_a, np.zeros(3)])
    p_b = pair.camera_b.K @ np.column_stack([r_b, -r_b @ pair.baseline_enu_m])
    homog = cv2.triangulatePoints(p_a, p_b, pair.pixels_a.T.astype(float), pair.pixels_b.T.astype(float))
    return (homog[:3] / homog[3]).T


def predicted_distance_error_m(
    distance_m: float, pair: StereoPair, disparity_sigma_px: float = 1.0, view_enu: np.ndarray | None = None
) -> float:
    """e_d of the module docstring for this pair's baseline.

    The disparity term needs the baseline *across* the line of sight (``view_enu``, camera a to
    the objects; the optical axis when not given): a baseline component along the view adds no
    parallax. The scale term uses the whole baseline, whose length error scales every distance.
    """
    f = math.sqrt(pair.camera_a.fx * pair.camera_a.fy)
    baseline = np.asarray(pair.baseline_enu_m, float)
    b = float(np.linalg.norm(baseline))
    view = pair.r_enu_cam_a[:, 2] if view_enu is None else np.asarray(view_enu, float)
    view = view / np.linalg.norm(view)
    b_across = float(np.linalg.norm(baseline - (baseline @ view) * view))
    if b_across <= 1e-9:
        return math.inf
    return math.hypot(
        distance_m**2 / (f * b_across) * disparity_sigma_px, distance_m * pair.baseline_sigma_m / b
    )


def best_pair(pairs: list[StereoPair], disparity_sigma_px: float = 1.0) -> tuple[int, np.ndarray, float]:
    """The pair whose measured baseline minimises the predicted distance error.

    The predicted error needs the distance, which needs a pair: each pair's own median
    triangulated distance and mean viewing direction are used. Returns (index, its object
    points, predicted error m).
    """
    if not pairs:
        raise OrthonavError("two-UAV stereo: no frame pair to choose from")
    best = (-1, np.zeros((0, 3)), math.inf)
    for i, pair in enumerate(pairs):
        points, error = triangulate_with_error(pair, disparity_sigma_px)
        if error < best[2]:
            best = (i, points, error)
    return best


def triangulate_with_error(pair: StereoPair, disparity_sigma_px: float = 1.0) -> tuple[np.ndarray, float]:
    """The pair's object points and its predicted distance error (m) at their median distance."""
    points = triangulate(pair)
    distances = np.linalg.norm(points, axis=1)
    view = np.mean(points / distances[:, None], axis=0)
    return points, predicted_distance_error_m(float(np.median(distances)), pair, disparity_sigma_px, view)


def sizes_m(points: np.ndarray, index_pairs: np.ndarray) -> np.ndarray:
    """Sizes (lengths between object points) for the given (M, 2) point index pairs."""
    return np.linalg.norm(points[index_pairs[:, 0]] - points[index_pairs[:, 1]], axis=1)
