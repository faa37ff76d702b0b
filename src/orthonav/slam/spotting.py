"""The other UAV in a frame: drawn into the picture, then found again by image processing.

The vehicle seen is a quadcopter in a fluorescent-orange ring (a prop guard) whose outer
diameter is its known span. Seen from any direction the ring is an ellipse whose major axis
lies across the line of sight, so the major axis in pixels is ``f * span / depth`` whatever
the vehicle's heading and the viewing angle: the range follows from it, the bearing from the
ellipse centre.

:func:`composite_uav` draws the vehicle (a top-down texture in its horizontal body plane)
through the camera's projection, occluding the ground, anti-aliased by supersampling; the
frame's photometric change (blur, noise, colour) is applied by the caller afterwards.
:func:`detect_uav` segments saturated orange in HSV, fits ellipses to the outer contours
(OpenCV), keeps candidates shaped like a ring seen from above and, when an expected span is
known (the tracker's prediction), of a plausible size; it refuses blobs cut by the frame
edge and those below a few pixels, saying why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from orthonav.camera import Camera, CameraPose, rotation_enu_from_camera
from orthonav.slam.rig import enu_r_body
from orthonav.slam.stereo import Sighting

MIN_SPAN_PX = 6.0  # below this the ring is a smudge: no honest span can be measured
SUPERSAMPLE = 4
RING_INNER = 0.8  # inner / outer diameter of the ring
ORANGE_BGR = (0, 110, 255)
HUE_RANGE = (2, 24)  # OpenCV hue (0..180) of the ring under the photometric changes
MIN_SATURATION = 130
MIN_VALUE = 110
MIN_AXIS_RATIO = 0.25  # the ring seen no lower than about 15 deg above its plane
SPAN_GATE = 2.0  # with an expected span, accept candidates within this factor of it
EDGE_MARGIN_PX = 1
EDGE_CORRECTION_PX = 0.5  # calibrated on renders at 10-80 px spans (mean span error ~0)
MIN_CONTRAST = 60.0  # ring minus ground in R - B (0..255)


@dataclass(frozen=True)
class Detection:
    """The detector's answer: a sighting, or None with the reason; candidates it considered."""

    sighting: Sighting | None
    reason: str
    candidates: int = 0

    @property
    def found(self) -> bool:
        return self.sighting is not None


def draw_uav_topdown(size_px: int) -> tuple[np.ndarray, np.ndarray]:
    """(size, size, 3) BGR texture and (size, size) alpha in [0, 1] of the vehicle seen from above,
    nose up: an orange ring (outer diameter = the texture), four dark rotor discs (half-transparent,
    spinning), black arms and a white body with a black centre mark."""
    n = int(size_px)
    bgr = np.zeros((n, n, 3), np.uint8)
    alpha = np.zeros((n, n), np.uint8)
    c, r = (n - 1) / 2.0, n / 2.0
    shift = 4  # sub-pixel drawing
    scale = 1 << shift

    def pt(x: float, y: float) -> tuple[int, int]:
        return round(x * scale), round(y * scale)

    def disc(image: np.ndarray, x: float, y: float, radius: float, value, thickness: int = -1) -> None:
        cv2.circle(image, pt(x, y), round(radius * scale), value, thickness, cv2.LINE_AA, shift)

    rotor = 0.26 * r
    for angle in (45, 135, 225, 315):
        x, y = c + 0.52 * r * math.cos(math.radians(angle)), c + 0.52 * r * math.sin(math.radians(angle))
        disc(bgr, x, y, rotor, (60, 60, 60))
        disc(alpha, x, y, rotor, 150)
        arm = max(1, round(0.08 * r))  # thickness is in whole pixels
        cv2.line(bgr, pt(c, c), pt(x, y), (10, 10, 10), arm, cv2.LINE_AA, shift)
        cv2.line(alpha, pt(c, c), pt(x, y), 255, arm, cv2.LINE_AA, shift)
    disc(bgr, c, c, 0.2 * r, (245, 245, 245))
    disc(alpha, c, c, 0.2 * r, 255)
    disc(bgr, c, c, 0.08 * r, (0, 0, 0))
    ring = (1 + RING_INNER) / 2 * r
    width = max(1, round((1 - RING_INNER) * r))
    cv2.circle(bgr, pt(c, c), round(ring * scale), ORANGE_BGR, width, cv2.LINE_AA, shift)
    cv2.circle(alpha, pt(c, c), round(ring * scale), 255, width, cv2.LINE_AA, shift)
    return bgr, alpha.astype(np.float32) / 255.0


def project_points(camera: Camera, pose: CameraPose, points_enu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) pixels and (N,) depths of ENU points (pinhole; the spotter has no distortion)."""
    r_cw = rotation_enu_from_camera(pose.yaw_deg, pose.pitch_deg, pose.roll_deg).T
    p = (r_cw @ (np.asarray(points_enu, float) - [pose.east_m, pose.north_m, pose.alt_agl_m]).T).T
    depth = p[:, 2]
    pixels = (camera.K @ (p / depth[:, None]).T).T[:, :2]
    return pixels, depth


def composite_uav(
    frame: np.ndarray,
    camera: Camera,
    pose: CameraPose,
    uav_enu: np.ndarray,
    uav_yaw_deg: float,
    span_m: float,
) -> np.ndarray:
    """The frame with the other UAV drawn where the camera sees it (a copy; unchanged when it is
    behind the camera or entirely outside the frame)."""
    half = span_m / 2.0
    corners_body = np.array([[half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0], [-half, -half, 0.0]])
    corners_enu = (enu_r_body(uav_yaw_deg) @ corners_body.T).T + np.asarray(uav_enu, float)
    pixels, depth = project_points(camera, pose, corners_enu)
    if np.any(depth <= 1.0):
        return frame.copy()
    x0, y0 = np.floor(pixels.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(pixels.max(axis=0)).astype(int) + 2
    h, w = frame.shape[:2]
    if x1 <= 0 or y1 <= 0 or x0 >= w or y0 >= h:
        return frame.copy()
    span_px = float(np.max(np.linalg.norm(pixels - pixels.mean(axis=0), axis=1)) * math.sqrt(2.0))
    size = int(min(1024, max(16, math.ceil(SUPERSAMPLE * span_px))))
    texture, alpha = draw_uav_topdown(size)
    # Texture corners (pixel edges, index coordinates) to supersampled ROI coordinates.
    tex = np.array(
        [[-0.5, -0.5], [size - 0.5, -0.5], [size - 0.5, size - 0.5], [-0.5, size - 0.5]], np.float32
    )
    roi = (pixels - [x0, y0]) * SUPERSAMPLE - 0.5
    homography = cv2.getPerspectiveTransform(tex, roi.astype(np.float32))
    big = ((x1 - x0) * SUPERSAMPLE, (y1 - y0) * SUPERSAMPLE)
    colour = cv2.warpPerspective(texture, homography, big, flags=cv2.INTER_LINEAR)
    weight = cv2.warpPerspective(alpha, homography, big, flags=cv2.INTER_LINEAR)
    premultiplied = colour.astype(np.float32) * weight[..., None]
    small = (x1 - x0, y1 - y0)
    colour_small = cv2.resize(premultiplied, small, interpolation=cv2.INTER_AREA)
    weight_small = cv2.resize(weight, small, interpolation=cv2.INTER_AREA)[..., None]
    out = frame.copy()
    fx0, fy0, fx1, fy1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    sub = (slice(fy0 - y0, fy1 - y0), slice(fx0 - x0, fx1 - x0))
    ground = out[fy0:fy1, fx0:fx1].astype(np.float32)
    blended = colour_small[sub] + ground * (1.0 - weight_small[sub])
    out[fy0:fy1, fx0:fx1] = np.clip(blended + 0.5, 0, 255).astype(np.uint8)
    return out


def orange_mask(bgr: np.ndarray) -> np.ndarray:
    """uint8 mask of saturated orange pixels: the ring's colour, rare on the ground."""
    hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
    lo = np.array([HUE_RANGE[0], MIN_SATURATION, MIN_VALUE], np.uint8)
    hi = np.array([HUE_RANGE[1], 255, 255], np.uint8)
    return cv2.inRange(hsv, lo, hi)


def detect_uav(
    bgr: np.ndarray, min_span_px: float = MIN_SPAN_PX, expected_span_px: float | None = None
) -> Detection:
    """Find the ringed UAV: its centre (continuous pixel coordinates, pixel centres at i + 0.5) and
    its span (the fitted ellipse's major axis), or None with the reason."""
    mask = cv2.morphologyEx(orange_mask(bgr), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    h, w = mask.shape
    candidates, reasons = [], []
    for contour in contours:
        x, y, bw, bh = cv2.boundingRect(contour)
        if len(contour) < 5:
            reasons.append(f"a blob of {max(bw, bh)} px, too small (< {min_span_px:g} px)")
            continue
        if (
            x < EDGE_MARGIN_PX
            or y < EDGE_MARGIN_PX
            or x + bw > w - EDGE_MARGIN_PX
            or y + bh > h - EDGE_MARGIN_PX
        ):
            reasons.append(f"a blob of {max(bw, bh)} px cut by the frame edge")
            continue
        ellipse = _half_contrast_ellipse(bgr, mask, (x, y, bw, bh))
        if ellipse is None:
            reasons.append(f"a blob of {max(bw, bh)} px without ring contrast")
            continue
        (cx, cy), major, minor, fill = ellipse
        if major < min_span_px:
            reasons.append(f"a blob of {major:.1f} px, too small (< {min_span_px:g} px)")
            continue
        if minor / major < MIN_AXIS_RATIO:
            reasons.append(f"a {major:.1f} px blob too elongated for a ring ({minor / major:.2f})")
            continue
        if expected_span_px and not (1 / SPAN_GATE <= major / expected_span_px <= SPAN_GATE):
            reasons.append(f"a {major:.1f} px blob where about {expected_span_px:.1f} px was expected")
            continue
        candidates.append((fill, cx, cy, major))
    if not candidates:
        if not contours:
            return Detection(
                None, "not detected: no ring-coloured pixels (no UAV in view, or too small and blurred)"
            )
        return Detection(None, "not detected: rejected " + "; ".join(reasons[:3]), 0)
    # The ring's outer contour fills its own ellipse; clutter rarely does.
    fill, u, v, major = max(candidates)
    return Detection(Sighting((float(u), float(v)), float(major)), "detected", len(candidates))


def _half_contrast_ellipse(
    bgr: np.ndarray, mask: np.ndarray, box: tuple[int, int, int, int]
) -> tuple[tuple[float, float], float, float, float] | None:
    """The blob's outline where the orangeness (R - B, linear in how much of a pixel the ring
    covers) is half-way between the ground around it and the ring: blur moves that level little,
    unlike a saturation threshold. Returns the centre (continuous coordinates), the major and
    minor axes (px) and how well the outline fills its ellipse, or None without contrast."""
    x, y, bw, bh = box
    pad = 4
    y0, y1, x0, x1 = (
        max(y - pad, 0),
        min(y + bh + pad, mask.shape[0]),
        max(x - pad, 0),
        min(x + bw + pad, mask.shape[1]),
    )
    roi = bgr[y0:y1, x0:x1].astype(np.float32)
    orangeness = roi[..., 2] - roi[..., 0]
    border = np.concatenate([orangeness[0], orangeness[-1], orangeness[:, 0], orangeness[:, -1]])
    ground = float(np.median(border))
    ring = float(np.percentile(orangeness[mask[y0:y1, x0:x1] > 0], 90))
    if ring - ground < MIN_CONTRAST:
        return None
    binary = (orangeness > (ground + ring) / 2).astype(np.uint8)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contours = [c for c in contours if len(c) >= 5]
    if not contours:
        return None
    outline = max(contours, key=cv2.contourArea)
    (cx, cy), axes, _ = cv2.fitEllipse(outline)
    # Contour points are the outermost pixels' centres, inside the half-contrast edge.
    major, minor = max(axes) + EDGE_CORRECTION_PX, min(axes) + EDGE_CORRECTION_PX
    fill = cv2.contourArea(outline) / (math.pi / 4 * major * minor)
    return (cx + x0 + 0.5, cy + y0 + 0.5), major, minor, fill
